"""Smoke test of ``python -m benchmarks optim`` at a tiny budget (the benchmark itself is not a test)."""

from __future__ import annotations

import json

import pytest

from benchmarks.cli import main


def test_bench_optim_json_has_every_method_and_a_verdict(capsys: pytest.CaptureFixture[str]) -> None:
    rc = main(
        [
            "optim",
            "--json",
            "--seeds",
            "2",
            "--budget",
            "200",
            "--popsize",
            "10",
            "--dim",
            "5",
            "--functions",
            "F1",
            "--no-peer",
        ]
    )
    assert rc == 0
    out = json.loads(capsys.readouterr().out)
    assert set(out["functions"]) == {"F1", "F1s"}
    for res in out["functions"].values():
        assert set(res) == {"igwo-paper", "igwo-normalized", "gwo", "woa", "ga"}
        for m in res.values():
            assert m["nfev_median"] <= 200
            assert m["fun"]["q25"] <= m["fun"]["median"] <= m["fun"]["q75"]
    assert "Paper's ranking" in out["verdict"]["summary"]
    assert out["peer"].startswith("peer skipped")
