"""The heap a long-running process starts with, kept out of the cyclic garbage collector's full passes.

A full (generation 2) pass of CPython's collector visits every tracked object while holding the GIL. A host
of 50 spindles starts with ~1.3 million of them (models, operators, modules, settings), so each full pass
stopped every thread of the process for ~1 s (measured: docs/design/fleet.md, "Whole-process stalls"): the
event loop's lag limit (0.25 s) was passed about once a minute and every spindle's ``event_loop`` went
degraded. :func:`freeze_startup_heap` runs once the process has started what it serves: one collection,
then ``gc.freeze()`` moves every object still alive into the permanent generation, which later passes do
not visit. Frozen objects are still freed when their reference count falls to 0; only a reference cycle
among objects alive at the freeze and dropped later is never reclaimed (a start-up's objects live as long
as the process). ``gc.freeze`` is documented to move every tracked object "to a permanent generation and
ignore them in all the future collections".
"""

from __future__ import annotations

import gc
from collections.abc import Callable
from dataclasses import dataclass

__all__ = ["FrozenHeap", "freeze_startup_heap"]


@dataclass(frozen=True)
class FrozenHeap:
    """What a freeze moved out of the collector's passes: ``objects`` now in the permanent generation."""

    objects: int

    def message(self) -> str:
        return f"kept {self.objects} start-up objects out of the garbage collector's full passes"


def freeze_startup_heap(
    *,
    collect: Callable[[], int] = gc.collect,
    freeze: Callable[[], None] = gc.freeze,
    frozen: Callable[[], int] = gc.get_freeze_count,
) -> FrozenHeap:
    """Collect once (so no garbage is frozen), then freeze what is alive. Call it once per process, after
    start-up; the collector's functions are injected for tests."""
    collect()
    freeze()
    return FrozenHeap(objects=frozen())
