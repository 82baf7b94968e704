"""The live state's kept snapshots (``service.estimate.state.FilteredState``): one every ``every_s`` for
``keep_s`` (where identification windows may start: ``at``, ``first_after``) and the last ``recent_steps``
steps (``mark`` keeps one of them, at a condition change). Pure: no I/O, no clock."""

from __future__ import annotations

from collections import deque
from typing import Generic, Protocol, TypeVar

from service.estimate.live import LiveStateError

__all__ = ["SnapshotBook"]


class Timed(Protocol):
    @property
    def t(self) -> float: ...


S = TypeVar("S", bound=Timed)


class SnapshotBook(Generic[S]):
    """See the module docstring; ``dt_s`` [s] the state's step (a snapshot up to half a step later counts)."""

    def __init__(self, *, keep_s: float, every_s: float, recent_steps: int, dt_s: float) -> None:
        self.every_s = float(every_s)
        self.dt_s = float(dt_s)
        self._snapshots: deque[S] = deque(maxlen=max(2, int(keep_s / every_s) + 2))
        self._recent: deque[S] = deque(maxlen=max(1, recent_steps))

    def clear(self) -> None:
        self._snapshots.clear()
        self._recent.clear()

    def keep(self, snap: S, *, force: bool = False) -> None:
        """A new step's estimate: kept as recent; as a snapshot when ``every_s`` has passed (or ``force``)."""
        self._recent.append(snap)
        if force or not self._snapshots or snap.t - self._snapshots[-1].t >= self.every_s - 1e-9:
            self._snapshots.append(snap)

    def mark(self, t: float) -> S | None:
        """Keep the estimate of the latest recent step at or before ``t`` [s] as a snapshot (a window can
        start there); none recent: the latest kept snapshot at or before ``t``; None: none that old."""
        older = [s for s in self._recent if s.t <= t + 0.5 * self.dt_s]
        if not older:
            kept = [s for s in self._snapshots if s.t <= t + 0.5 * self.dt_s]
            return kept[-1] if kept else None
        snap = older[-1]
        if all(s.t != snap.t for s in self._snapshots):
            kept = sorted([*self._snapshots, snap], key=lambda s: s.t)
            self._snapshots.clear()
            self._snapshots.extend(kept[-(self._snapshots.maxlen or len(kept)) :])
        return snap

    def at(self, t: float) -> S:
        """The latest snapshot at or before ``t`` [s], up to half a step later (sample-time jitter)."""
        older = [s for s in self._snapshots if s.t <= t + 0.5 * self.dt_s]
        if not older:
            raise LiveStateError(f"no live-state snapshot at or before t={t:.0f} s")
        return older[-1]

    def first_after(self, t: float) -> S:
        """The earliest snapshot at or after ``t`` [s]."""
        newer = [s for s in self._snapshots if s.t >= t - 1e-9]
        if not newer:
            raise LiveStateError(f"no live-state snapshot at or after t={t:.0f} s")
        return newer[0]
