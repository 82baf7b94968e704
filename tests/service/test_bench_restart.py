"""``python -m benchmarks restart``: the aggregation over seeds and the command's registration (the full bench
is a measurement; docs/design/estimator.md has its figures)."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from benchmarks import restart
from benchmarks.restart import Served
from benchmarks.restart_filter import FilterRestart
from benchmarks.restart_profile import DT_S
from model.plant import Segment
from service.host.runtime import core_config
from service.modelload import LoadedModel
from service.settings import Settings
from tests.service.conftest import plant_run


def _served(speed: float, factor: np.ndarray, end_s: float, ci: float = 0.1) -> Served:
    h = restart.truth(speed) * factor
    return Served(speed_rpm=speed, h=h, lo=h * (1 - ci), hi=h * (1 + ci), end_s=end_s)


def test_summary_takes_each_conditions_last_result_per_seed() -> None:
    ones = np.ones(7)
    off = np.r_[1.5, np.ones(6)]  # H1 50 % high: its CI (±10 %) misses
    seeds = [
        [_served(3000.0, off, 1200.0), _served(3000.0, ones, 3900.0), _served(4000.0, off, 6000.0)],
        [_served(3000.0, ones * 1.02, 2400.0), _served(4000.0, ones, 6600.0)],
    ]
    out = restart.summarise(seeds, start_s=600.0)
    assert out["first_served_min"] == pytest.approx((np.median([1200.0, 2400.0]) - 600.0) / 60.0, abs=0.05)
    c3, c4, c5 = out["conditions"]
    assert c3["seeds_served"] == 2 and c3["covers_all"] == 1.0
    assert c3["h_err_pct_median"] == pytest.approx([1.0] * 7)  # median of 0 % and 2 %
    assert c4["coverage"][0] == 0.5 and c4["coverage"][1:] == [1.0] * 6 and c4["covers_all"] == 0.5
    assert c4["h_err_pct_median"][0] == pytest.approx(25.0)
    assert c4["ci_half_width_pct_median"] == [10.0] * 7
    assert c5 == {"speed_rpm": 5000.0, "seeds_served": 0}
    # the first served H: seed 1's after 10 min (H1 50 % high, missed), seed 2's after 30 min (all covered)
    assert out["first_served_min_max"] == pytest.approx(30.0)
    first = out["first"]
    assert first["speeds_rpm"] == [3000.0]
    assert first["coverage"] == [0.5] + [1.0] * 6 and first["ci_half_width_pct_median"] == [10.0] * 7
    assert "identified_frac" not in first  # no flags given (filter mode)


def test_first_served_h_flags_are_counted() -> None:
    flags = np.r_[True, False, True, True, True, True, True]
    seeds = [
        [
            Served(
                speed_rpm=4000.0,
                h=restart.truth(4000.0),
                lo=restart.truth(4000.0) * 0.5,
                hi=restart.truth(4000.0) * 2.0,
                end_s=1500.0,
                identified=flags,
            )
        ],
        [],  # a seed that served nothing is left out
    ]
    out = restart.summarise(seeds, start_s=900.0)
    assert out["first_served_min"] == out["first_served_min_max"] == pytest.approx(10.0)
    assert out["first"]["identified_frac"] == [1.0, 0.0] + [1.0] * 5
    assert out["first"]["first_identified_min"] == pytest.approx(10.0)
    assert out["first"]["first_identified_seeds"] == 0.5  # of the two seeds, one had an H identified
    assert out["first"]["ci_half_width_pct_median"] == [75.0] * 7
    assert restart.summarise([[], []], start_s=0.0)["first"] is None


def test_ratios_against_the_start_at_minute_zero() -> None:
    starts = [
        {"start_min": 0, "conditions": [{"speed_rpm": 4000.0, "h_err_pct_median": [10.0] * 6 + [0.0]}]},
        {"start_min": 60, "conditions": [{"speed_rpm": 4000.0, "h_err_pct_median": [15.0] * 6 + [0.2]}]},
    ]
    restart.add_ratios(starts)
    assert "h_err_ratio_vs_start0" not in starts[0]["conditions"][0]
    assert starts[1]["conditions"][0]["h_err_ratio_vs_start0"] == [1.5] * 6 + [2.0]  # 0 % floored at 0.1 %


def test_command_is_registered_and_checks_its_arguments(capsys: pytest.CaptureFixture[str]) -> None:
    from benchmarks import cli

    with pytest.raises(SystemExit):
        cli.main(["restart", "--help"])
    assert "--start-modes" in capsys.readouterr().out
    assert cli.main(["restart", "--starts", "200"]) == 2
    assert "outside the profile" in capsys.readouterr().err
    # the identification mode (--mode per_condition|speed_map) and the path (--path core|filter)
    assert cli.main(["restart", "--path", "filter", "--mode", "speed_map"]) == 2
    assert "per-condition protocol only" in capsys.readouterr().err
    assert cli.main(["restart", "--path", "core", "--mode", "filter"]) == 2  # the old spelling
    assert "contradicts" in capsys.readouterr().err
    assert cli.main(["restart", "--set", "nope=1"]) == 2
    assert "unknown setting nope" in capsys.readouterr().err


class _Gate(FilterRestart):
    """The filter path with its identification recorded instead of run (the gate before it is what counts)."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.asked: list[float] = []

    def _identify(self, state: Any, cond_start: int, end: int, *_: Any) -> Any:
        self.asked.append(float(self.run_data.speed_rpm[end - 1]))
        return None


def test_filter_path_skips_the_windows_the_core_skips_and_no_others(loaded_model: LoadedModel) -> None:
    """The filter path takes the core's rules (``core_config``), not a copy: a slow condition the core
    identifies (above ``CoreConfig.min_speed_rpm``, 100 rpm) is identified here too, an idle one is not (the
    copy skipped everything below 500 rpm)."""
    settings = Settings()
    core = core_config(settings)
    slow = 3.0 * core.min_speed_rpm  # 300 rpm: identified by the core, skipped by the old copy's 500 rpm
    assert slow < 500.0
    run = plant_run([Segment(300.0, 0.0, 0.0, 22.0), Segment(1800.0, slow, 1.0, 22.0)])
    assert np.allclose(np.diff(run.times_s), DT_S)
    gate = _Gate(loaded_model, settings, run, seed=0)
    assert gate.core.min_speed_rpm == core.min_speed_rpm
    gate.run(0)
    assert gate.asked and set(gate.asked) == {slow}
