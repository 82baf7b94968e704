"""``python -m benchmarks growth``: its duty profile and its registration (the bench itself is run by
hand)."""

from __future__ import annotations

import numpy as np

from benchmarks.cli import build_parser
from benchmarks.growth import CHAIN, DT_S, _Rows, duty_profile, summarise


def test_duty_profile_is_seeded_and_in_range() -> None:
    a, b = duty_profile(0), duty_profile(1)
    assert a == duty_profile(0) and a != b
    for prof in (a, b):
        idle, warm, *duty = prof
        assert idle[1] == 0.0 and warm[1] == 4000.0 and warm[0] >= 1800.0  # an identification can exist
        d = np.array(duty)
        assert np.all((d[:, 0] >= 60.0) & (d[:, 0] <= 360.0)) and np.all(d[:, 0] % DT_S == 0)
        assert np.all((d[:, 1] >= 0.0) & (d[:, 1] <= 7000.0))
        assert np.all((d[:, 2] >= 3.0) & (d[:, 2] <= 15.0))
        assert np.all(np.abs(d[:, 3] - idle[3]) <= 1.0 + 1e-9) and np.ptp(d[:, 3]) > 0.2
        assert d[:, 0].sum() >= 5400.0


def test_summary_of_rows() -> None:
    rows = _Rows(axial_err=[0.5, -1.5, 3.0], axial_in=[True, True, False], radial_err=[0.1], radial_in=[True])
    rows.horizon_err[30] += [0.2, -0.4]
    out = summarise(rows)
    assert out["axial_err_um_median"] == 1.5 and out["axial_err_um_max"] == 3.0
    assert out["coverage"] == round(2 / 3, 3)
    assert out["forecast_err_um"]["5min"] == {"median": 0.3, "max": 0.4, "n": 2}
    assert out["steady_forecast_covered"] is None  # not measured, not 0


def test_registered_as_a_bench() -> None:
    args = build_parser(["growth", "--seeds", "2", "--json"]).parse_args(["growth", "--seeds", "2", "--json"])
    assert args._module.__name__ == "benchmarks.growth" and args.seeds == 2 and args.json
    assert CHAIN[0][1] == 0.0  # starts idle and cold, like the chain bench


def test_plant_mechanics_option_defaults_to_drawn() -> None:
    parse = build_parser(["growth"]).parse_args
    assert parse(["growth"]).plant_mechanics == "drawn"
    assert parse(["growth", "--plant-mechanics", "nominal"]).plant_mechanics == "nominal"
