"""What of a restored state may resume at the first new sample: nothing dated after it.

A clock stepped back (NTP, a replaced controller PC, a replay of an older log, a demo re-run on its own
database with its accelerated clock) makes the database hold a live-state checkpoint, conditions and
identifications dated after the samples now arriving. The live state cannot predict backwards, a condition
cannot start before its own start, and an identification cannot serve before its window: such items are not
resumed and the state starts from its prior (said once in the log). The ids stay the database's (the rows are
still there: new ones continue after them). Pure: no I/O, no clock.
"""

from __future__ import annotations

from dataclasses import replace
from datetime import UTC, datetime

from service.core.config import Restored

__all__ = ["cut_future"]


def cut_future(restored: Restored, t: float) -> tuple[Restored, list[str]]:
    """``restored`` without what is dated after the sample time ``t`` [s, UTC epoch], and the lines that say
    what was left out (none: ``restored`` itself)."""
    notes: list[str] = []
    at = datetime.fromtimestamp(t, UTC).isoformat(timespec="seconds")
    out = restored
    if restored.live is not None and restored.live.t > t + 1e-6:
        when = datetime.fromtimestamp(restored.live.t, UTC).isoformat(timespec="seconds")
        notes.append(
            f"live state not resumed: its checkpoint of {when} is after the first sample ({at}; the clock "
            "went back?); it starts from its prior"
        )
        out = replace(out, live=None)
    kept = tuple(c for c in restored.conditions if c.since.timestamp() <= t)
    if len(kept) != len(restored.conditions):
        notes.append(
            f"{len(restored.conditions) - len(kept)} stored condition(s) dated after the first sample ({at}) "
            "not resumed"
        )
        out = replace(out, conditions=kept)
    out, dropped = _identifications(out, t)
    if dropped:
        notes.append(
            f"stored identification(s) {', '.join(str(i) for i in dropped)} dated after the first sample "
            f"({at}) not resumed: H starts from the prior"
        )
    return out, notes


def _identifications(restored: Restored, t: float) -> tuple[Restored, list[int]]:
    """Drop the served identification and the map fit whose window ends after ``t``."""
    dropped: list[int] = []
    out = restored
    last, map_last = restored.last, restored.map_last
    if last is not None and last.window_to.timestamp() > t:
        dropped.append(last.id)
        out = replace(out, last=None)
    if map_last is not None and map_last.window_to.timestamp() > t:
        if map_last is not last:
            dropped.append(map_last.id)
        out = replace(out, map_last=None, speed_map=None)
    return out, dropped
