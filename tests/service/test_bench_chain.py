"""``python -m benchmarks chain``: its summary arithmetic, and a one-seed run of the command (shape and
sanity)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from benchmarks.chain import summarise
from benchmarks.cli import main


def test_summarise_per_h_over_seeds() -> None:
    err = np.array([[0.1, -0.5], [-0.3, 0.2], [0.2, 0.0]])
    half = np.array([[0.05, 0.4], [0.07, 0.2], [0.09, 0.3]])
    cov = np.array([[True, False], [False, True], [True, True]])
    out = summarise(err, half, cov)
    assert out["h_err_pct_median"] == [20.0, 20.0]
    assert out["h_err_pct_max"] == [30.0, 50.0]
    assert out["ci_half_width_pct_median"] == [7.0, 30.0]
    assert out["ci_coverage"] == [0.67, 0.67]
    assert out["ci_covers_all"] == 0.33 and out["ci_covers_all_but_one"] == 1.0
    # per seed, the median |error| over its H: 30, 25, 10 %
    assert out["seed_median_err_pct_median"] == 25.0 and out["seed_median_err_pct_max"] == 30.0


@pytest.mark.slow
@pytest.mark.parametrize("mode", ["per_condition", "speed_map"])
def test_bench_chain_one_seed(mode: str, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["chain", "--seeds", "1", "--mode", mode, "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["synthetic"] is True and out["mode"] == mode
    assert out["window_min"] == (40 if mode == "per_condition" else 60)
    assert [c["speed_rpm"] for c in out["conditions"]] == [3000.0, 4000.0, 5000.0]
    for c in out["conditions"]:
        assert c["seeds"] == 1 and len(c["h_err_pct_median"]) == 7
        assert all(0.0 <= x <= 1.0 for x in c["ci_coverage"])
        assert min(c["h_err_pct_median"]) < 15.0  # the best-determined H (H6) is close to the truth
    assert main(["chain", "--seeds", "0"]) == 2
    assert main(["chain", "--set", "map_window_min=5"]) == 2  # < map_min_window_min
    assert "map_min_window_min" in capsys.readouterr().err
