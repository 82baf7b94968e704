"""Smoke test of ``python -m benchmarks identify`` with one seed everywhere (the benchmark itself is not a
test)."""

from __future__ import annotations

import json

import pytest

from benchmarks.cli import main


@pytest.mark.slow
def test_bench_identify_json_shape(capsys: pytest.CaptureFixture[str]) -> None:
    args = [
        "identify",
        "--json",
        "--seeds",
        "1",
        "--ci-seeds",
        "1",
        "--warm-seeds",
        "1",
        "--skip-28x150",
    ]
    assert main(args) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["data"].startswith("SYNTHETIC")
    assert [(c["speed_rpm"], c["ambient_c"]) for c in out["conditions"]] == [(3000.0, 23.2), (4000.0, 21.8)]
    for cond in out["conditions"]:
        methods = cond["methods"]
        assert set(methods) == {"empirical", "ga", "woa", "gwo", "igwo", "hybrid"}
        assert min(m["objective_gap_pct"] for m in methods.values()) == 0.0
        for m in methods.values():
            assert len(m["h_err_pct"]) == 7
            assert set(m["test_points"]) == {"1", "3", "5", "7"}
        assert methods["hybrid"]["objective_gap_pct"] <= 0.1
    assert 0.0 <= out["ci_coverage_95"] <= 1.0
    assert out["warm_vs_cold_nfev_ratio"] > 0.0


@pytest.mark.slow
def test_bench_identify_tables_without_28x150_print_every_target(capsys: pytest.CaptureFixture[str]) -> None:
    """Without ``--json`` and with ``--skip-28x150`` the tables used to crash (TypeError on the skipped
    figure); now every target is printed with its verdict, the skipped one as not measured."""
    args = ["identify", "--seeds", "1", "--ci-seeds", "1", "--warm-seeds", "1", "--skip-28x150"]
    assert main(args) == 0
    out = capsys.readouterr().out
    assert "IGWO 28x150 on the reduced model: skipped" in out
    lines = out[out.index("targets:") :].splitlines()
    skipped = [line for line in lines if line.strip().startswith("igwo_28x150_wall_s <= 2 s")]
    assert len(skipped) == 1 and "not measured" in skipped[0]
    assert sum(line.rstrip().endswith(("met", "MISSED", "measured", "condition)")) for line in lines) >= 5
