"""Smoke test of the robustness bench (``python -m benchmarks.robustness``): one seed, the short thermal test,
short scenarios of two families; the JSON's keys and sane figures."""

from __future__ import annotations

import json

import pytest

from benchmarks.robustness.bench import main


@pytest.mark.slow
@pytest.mark.timeout(1800)  # minutes on 2 loaded cores
def test_one_seed_short_scenarios_give_every_key(capsys: pytest.CaptureFixture[str]) -> None:
    argv = ["--seeds", "1", "--short", "--hours", "0.5", "--rest-min", "20", "--json"]
    argv += ["--families", "sensors"]
    assert main(argv) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["seeds"] == [400]
    fam = out["families"]["sensors"]
    for method in ("none", "mlr", "ridge", "lasso", "arx", "product"):
        for key in ("rms_um", "p95_um", "max_um"):
            assert fam[method][key] is not None and fam[method][key] >= 0.0
    assert 0.0 <= fam["product"]["usable_fraction"] <= 1.0
    assert isinstance(fam["product"]["not_usable_minutes"], dict)
    assert out["pooled"]["rms_ratio_product_over_best_peer"] > 0.0
    assert out["faults"]["runs"] == 3
    assert "detect_min_median" in out["faults"]
    assert set(out["scenarios"]) == {"sensors.open", "sensors.stuck", "sensors.drift"}


def test_unknown_family_is_refused(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["--families", "ambient,weather"]) == 2
    assert "--families" in capsys.readouterr().err


def test_the_machine_familys_coverage_splits_at_the_first_reading() -> None:
    from benchmarks.robustness.bench import _coverage, _first

    row = {
        "t_min": [30.0, 31.0, 32.0, 33.0, 34.0],
        "usable": [True, True, False, True, True],
        "covered": [False, False, False, True, False],
        "probe": {"first_min": 31.0},
    }
    before = _coverage([row], lambda r, t: t <= _first(r))
    after = _coverage([row], lambda r, t: t > _first(r))
    assert before == {"coverage_usable": 0.0, "usable_fraction": 1.0, "minutes": 2}
    assert after == {"coverage_usable": 0.5, "usable_fraction": 0.667, "minutes": 3}
    assert _first({"probe": {"first_min": None}}) == float("inf")  # no reading: all before it
