"""``python -m benchmarks truth``: its random profiles and truths, and its summary arithmetic (no plant
run)."""

from __future__ import annotations

import numpy as np

from benchmarks.truth import H_LIMITS, REST_S, draw_levels, h_law, segments, summarise_raw, verdict
from model.plant import h_true


def test_levels_are_hidden_truths_with_fast_speeds_drift_and_a_torque_step() -> None:
    for seed in range(5):
        levels = draw_levels(np.random.default_rng(seed))
        speeds = [lv.speed_rpm for lv in levels]
        assert 3000 <= speeds[0] <= 5000 and all(6000 <= s <= 7000 for s in speeds[1:])
        assert speeds[1] == speeds[2] and levels[2].torque_nm > levels[1].torque_nm + 2.9  # the torque step
        assert abs(speeds[3] - speeds[1]) >= 300
        for lv in levels:
            assert np.all((lv.h >= H_LIMITS[0]) & (lv.h <= H_LIMITS[1]))
            assert not np.allclose(lv.h, h_true(lv.speed_rpm, lv.ambient_from_c), rtol=0.05)
            assert abs(lv.ambient_to_c - lv.ambient_from_c) <= 0.8
        segs = segments(levels, levels[0].ambient_from_c)
        assert segs[0].duration_s == REST_S and segs[0].speed_rpm == 0.0
        law = h_law(levels)
        np.testing.assert_array_equal(law(speeds[1], 20.0, 3.0), levels[1].h)


def test_summary_counts_coverage_flag_misses_and_all_seven() -> None:
    truth = [[10.0] * 7, [10.0] * 7]
    raw = {
        "truth": truth,
        "h": [[11.0] * 7, [8.0] * 7],
        "lo": [[9.0] * 7, [7.0] * 6 + [8.5]],
        "hi": [[12.0] * 7, [9.0] * 6 + [11.0]],
        "identified": [[True] * 7, [True, False, False, False, False, False, True]],
        "wall_s": [0.5, 0.7],
        "window_min": [40.0, 60.0],
    }
    out = summarise_raw(raw, 2)
    assert out["coverage"] == [0.5] * 6 + [1.0]
    assert out["h_err_pct_median"] == [15.0] * 7
    assert out["covers_all"] == 0.5
    assert out["flag_miss_fraction"] == round(1 / 9, 3)  # one of nine flagged H misses
    met = verdict("clean", out)
    assert met == {"coverage": False, "flag_miss": False, "wall_s": True, "covers_all": False}
