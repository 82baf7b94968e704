"""Benchmark targets and verdicts, printed the same way by every ``python -m benchmarks``.

A bench is not a test: a missed target is printed as ``MISSED`` (and in ``--json`` as ``"met": false``) and
the exit status stays 0. A figure that was not measured (e.g. ``--skip-28x150``) is ``not measured``.
"""

from __future__ import annotations

import json
import sys
from collections.abc import Callable, Iterable, Mapping
from dataclasses import KW_ONLY, dataclass
from typing import Any

__all__ = ["Target", "format_verdicts", "verdicts"]


@dataclass(frozen=True)
class Target:
    """``figure op limit`` with its unit, e.g. ``Target("rom_max_err_c", "<=", 0.05, unit="°C")``.

    ``op`` is ``<=``, ``>=`` or ``in`` (``limit`` then a (low, high) pair, both inclusive).
    """

    figure: str
    op: str
    limit: float | tuple[float, float]
    _: KW_ONLY
    unit: str = ""
    note: str = ""

    def met(self, value: float | None) -> bool | None:
        """True/False, or None when the figure was not measured."""
        if value is None:
            return None
        if self.op == "in":
            lo, hi = self.limit  # type: ignore[misc]
            return bool(lo <= value <= hi)
        assert isinstance(self.limit, int | float)
        return bool(value <= self.limit) if self.op == "<=" else bool(value >= self.limit)

    def text(self) -> str:
        unit = f" {self.unit}" if self.unit else ""
        if self.op == "in":
            lo, hi = self.limit  # type: ignore[misc]
            return f"{self.figure} in [{lo:g}, {hi:g}]{unit}"
        return f"{self.figure} {self.op} {self.limit:g}{unit}"


def verdicts(targets: Iterable[Target], values: Mapping[str, float | None]) -> list[dict[str, Any]]:
    """One JSON-ready verdict per target: target text, measured value, met (True/False/None)."""
    out = []
    for t in targets:
        value = values.get(t.figure)
        out.append(
            {
                "target": t.text(),
                "value": None if value is None else float(value),
                "met": t.met(value),
                "note": t.note,
            }
        )
    return out


def format_verdicts(items: list[dict[str, Any]]) -> str:
    """The verdict lines and a summary; an empty list says the bench has no targets."""
    if not items:
        return "targets: none (this bench reports figures only)"
    lines = ["targets:"]
    for v in items:
        state = {True: "met", False: "MISSED", None: "not measured"}[v["met"]]
        value = "-" if v["value"] is None else f"{v['value']:.4g}"
        note = f"  ({v['note']})" if v["note"] else ""
        lines.append(f"  {v['target']:<44} measured {value:>10}  {state}{note}")
    missed = sum(v["met"] is False for v in items)
    met = sum(v["met"] is True for v in items)
    lines.append(
        f"  {met} of {len(items)} met"
        + (f", {missed} MISSED" if missed else "")
        + (f", {len(items) - met - missed} not measured" if len(items) - met - missed else "")
    )
    return "\n".join(lines)


def report(out: dict[str, Any], *, as_json: bool, table: Callable[[dict[str, Any]], None]) -> int:
    """A bench command's output: ``out`` as indented JSON, or its ``table``; the exit code (0)."""
    if as_json:
        print(json.dumps(out, indent=2))
    else:
        table(out)
    return 0


def progress_to_stderr(msg: str) -> None:
    """A bench's progress line, on stderr so that ``--json`` stdout stays one object."""
    print(msg, file=sys.stderr, flush=True)
