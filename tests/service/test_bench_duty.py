"""``python -m benchmarks duty``: one short seed through the real service (shell, core, inline
identification), the aggregation and the command's registration (the full bench is a measurement;
docs/design/hmap.md has its figures)."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from benchmarks import duty
from simulator.duty import SPEEDS_RPM, condition_at, duty_profile


def test_duty_profile_is_seeded_and_within_the_issues_ranges() -> None:
    a = duty_profile(3, duration_s=4 * 3600.0)
    assert a == duty_profile(3, duration_s=4 * 3600.0) and a != duty_profile(4, duration_s=4 * 3600.0)
    assert sum(s.duration_s for s in a) == pytest.approx(4 * 3600.0)
    assert a[0].speed_rpm == 0.0 and a[0].duration_s == 300.0  # the idle start (offset baseline)
    run = a[1:-1]
    assert all(60.0 <= s.duration_s <= 360.0 and s.duration_s % 60.0 == 0 for s in run)
    assert all(s.speed_rpm in SPEEDS_RPM for s in a)
    assert all(b.speed_rpm != c.speed_rpm for b, c in itertools.pairwise(a))
    assert all(3.0 <= s.torque_nm <= 15.0 for s in a if s.speed_rpm > 0)
    amb = np.array([s.ambient_c for s in a])
    assert np.ptp(amb) <= 2.0 + 1e-9 and abs(np.mean(amb) - 22.0) < 1.0
    assert condition_at(a, 0.0) is a[0] and condition_at(a, 300.0) is a[1]


def test_longest_gap_and_summary() -> None:
    assert duty.longest_gap([True, False, False, True, False]) == 2
    assert duty.longest_gap([]) == 0
    r = duty.SeedResult(fresh=[True, True, False], wall_s=[0.5, 1.5], nfev=[4, 8], fits=2)
    r.err = [np.full(7, 0.1), np.full(7, -0.3)]
    r.covered = [np.ones(7, bool), np.r_[np.zeros(1, bool), np.ones(6, bool)]]
    r.identified = [np.ones(7, bool), np.ones(7, bool)]
    out = duty.summarise([r])
    assert out["fresh_fraction"] == pytest.approx(2 / 3, abs=1e-3) and out["longest_gap_min"] == 1
    assert out["h_err_pct_median"] == [20.0] * 7
    assert out["coverage"] == [0.5] + [1.0] * 6
    assert out["identify_wall_s_median"] == 1.0 and out["identify_wall_s_max"] == 1.5
    assert out["per_condition_fits_per_seed"] == 0.0 and out["per_condition_wall_s_median"] is None
    r.held_wall_s, r.held_served = [0.2, 0.4, 0.9], [True, False]
    out = duty.summarise([r])
    assert out["per_condition_fits_per_seed"] == 3.0 and out["per_condition_wall_s_max"] == 0.9
    assert out["per_condition_served_fraction"] == 0.5
    assert out["identify_wall_s_max"] == 1.5  # the map fits' own figures are not mixed with them


@pytest.mark.slow
def test_one_short_seed_through_the_service_in_map_mode() -> None:
    out = duty.run_bench([1], mode="speed_map", hours=0.6, warmup_min=20.0)
    keys = ("fresh_fraction", "longest_gap_min", "identify_wall_s_median", "identify_wall_s_max", "seeds")
    assert all(key in out for key in keys)
    assert out["seeds"] == 1 and len(out["coverage"]) == 7 and len(out["h_err_pct_median"]) == 7
    assert out["fits_per_seed"] >= 2  # the first after 10 min of data, then on changes
    assert out["fresh_fraction"] > 0.5
    assert out["h_err_pct_median"][5] < 30.0  # H6, the best determined


def test_command_is_registered_and_checks_its_arguments(capsys: pytest.CaptureFixture[str]) -> None:
    from benchmarks import cli

    with pytest.raises(SystemExit):
        cli.main(["duty", "--help"])
    assert "--mode" in capsys.readouterr().out
    assert cli.main(["duty", "--seeds", "0"]) == 2
    assert cli.main(["duty", "--set", "nokey"]) == 2
