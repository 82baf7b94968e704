"""``python -m benchmarks commission``: the pooled figures from hand-made rows, and one short seed end to end
(thermal test, commissioning, MLR, duty cycle through the service's core)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from benchmarks import commission as bc
from benchmarks.cli import main


def _row(seed: int, cal: list[float], mlr: list[float]) -> dict:
    n = len(cal)
    return {
        "seed": seed,
        "mechanics": [0.5, 1.0, 1.0],
        "fitted": [0.5, 1.0, 1.0],
        "mlr_sensors": [1, 2, 3, 4],
        "mlr_fit_rms_um": 0.1,
        "probe_fitted": [0.5, 1.0, 1.0],
        "probe_readings": 1,
        "probe_accepted": 1,
        "minutes": n + 1,  # the first minute with nothing served
        "err": {
            "none": [2.0] * (n + 1),
            "mlr": mlr,
            "uncalibrated": [math.nan] + [-1.0] * n,
            "calibrated": [math.nan, *cal],
            "probe": [math.nan, *cal],
        },
        "covered": {
            "calibrated": [True] * (n - 1) + [False],
            "uncalibrated": [False] * n,
            "probe": [True] * n,
        },
        "usable": {
            "calibrated": [False] + [True] * n,
            "uncalibrated": [False] * (n + 1),
            "probe": [False] + [True] * (n - 1) + [False],
        },
        "fit_s": 1.0,
        "mlr_fit_s": 0.01,
    }


def test_summary_pools_seeds_and_ratios_per_seed() -> None:
    out = bc.summarize([_row(0, [0.5, -0.5, 0.5, -0.5], [9.0] + [1.0] * 4), _row(1, [1.0] * 4, [-0.5] * 5)])
    assert out["seeds"] == [0, 1]
    # over the minutes the calibrated product served (the MLR's 9 µm of the first minute not counted)
    assert out["rms_ratio_calibrated_over_mlr"] == [0.5, 2.0]
    assert out["seeds_ratio_at_most_half"] == 1
    assert out["none"]["rms_um"] == 2.0
    assert out["uncalibrated"]["removed"] == 0.5
    assert out["calibrated"]["coverage"] == 0.75
    assert out["calibrated"]["usable_fraction"] == 0.8
    assert out["calibrated"]["err_um_median"] == pytest.approx(0.75)
    assert out["uncalibrated"]["usable_fraction"] == 0.0
    assert out["uncalibrated"]["err_um_p95_usable"] is None
    assert out["probe"]["coverage"] == 1.0
    assert out["probe"]["usable_fraction"] == 0.6  # 3 of 5 minutes per seed
    assert out["probe"]["err_um_p95"] == out["calibrated"]["err_um_p95"]
    assert out["probe"]["p95_reduction"] == 0.0


@pytest.mark.slow
def test_one_short_seed_end_to_end(capsys: pytest.CaptureFixture[str]) -> None:
    argv = ["commission", "--seeds", "1", "--short", "--hours", "1", "--rest-min", "10"]
    argv += ["--probe-min", "20", "--json"]
    assert main(argv) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["seeds"] == [0]
    for m in ("none", "mlr", "uncalibrated", "calibrated", "probe"):
        for k in ("err_um_median", "err_um_p95", "err_um_max", "rms_um"):
            assert math.isfinite(out[m][k]) and out[m][k] >= 0.0
    for m in ("calibrated", "uncalibrated", "probe"):
        assert 0.0 <= out[m]["coverage"] <= 1.0
    # served as /compensation serves it: the commissioned product is usable, the uncommissioned never is
    # (compensation.require_mechanics_calibration), and says why
    for m in ("calibrated", "probe"):
        assert 0.5 <= out[m]["usable_fraction"] <= 1.0
    assert out["uncalibrated"]["usable_fraction"] == 0.0
    seed = out["per_seed"][0]
    assert seed["not_usable"]["uncalibrated"] == {"mechanics_uncalibrated": seed["minutes"]}
    assert seed["restart_min"] == 35  # half-way through the 50 min of machining
    assert out["calibrated"]["err_um_median"] < out["none"]["err_um_median"]
    assert out["calibrated"]["rms_um"] < out["none"]["rms_um"]
    assert out["mlr"]["rms_um"] < out["none"]["rms_um"]
    ratio = out["rms_ratio_calibrated_over_mlr"]
    assert len(ratio) == 1 and np.isfinite(ratio[0])
    assert out["per_seed"][0]["probe_readings"] == 2  # minutes 20 and 40 of the 50 after the rest
    assert out["probe"]["err_um_median"] < out["none"]["err_um_median"]
    assert 4 <= len(out["per_seed"][0]["mlr_sensors"]) <= 6
    assert out["fit_wall_s"]["product"][0] > 0
