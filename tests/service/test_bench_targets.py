"""Bench targets: a missed target says MISSED, an unmeasured one says so, the exit status is not touched."""

from __future__ import annotations

from benchmarks.targets import Target, format_verdicts, verdicts


def test_verdicts_met_missed_and_not_measured() -> None:
    targets = (
        Target("a_s", "<=", 1.0, unit="s"),
        Target("b", ">=", 2.0),
        Target("c", "in", (0.85, 1.0)),
        Target("d_s", "<=", 2.0, unit="s"),
    )
    items = verdicts(targets, {"a_s": 1.5, "b": 2.0, "c": 0.9})
    assert [v["met"] for v in items] == [False, True, True, None]
    text = format_verdicts(items)
    assert "a_s <= 1 s" in text and "MISSED" in text.splitlines()[1]
    assert "not measured" in text.splitlines()[4]
    assert text.splitlines()[-1].strip() == "2 of 4 met, 1 MISSED, 1 not measured"


def test_a_bench_without_targets_says_so() -> None:
    assert format_verdicts([]).startswith("targets: none")
