"""The start-up heap kept out of the collector's full passes (service/shell/heap.py; docs/design/fleet.md,
"Whole-process stalls"). Run in a child interpreter: a freeze is process-wide and lasts for its life."""

from __future__ import annotations

import json
import subprocess
import sys

from service.shell.heap import freeze_startup_heap

_CHILD = """
import gc, json
from service.shell.heap import freeze_startup_heap

class Node:
    def __init__(self):
        self.me = self  # a reference cycle: only the cyclic collector frees it

startup = [Node() for _ in range(20000)]          # what a start-up leaves alive
garbage = [Node() for _ in range(100)]; del garbage  # cyclic garbage from start-up: collected, not frozen
before = len(gc.get_objects(generation=2))
heap = freeze_startup_heap()
after = len(gc.get_objects(generation=2))
later = Node(); del later                           # cyclic garbage made after the freeze: still collected
print(json.dumps({"frozen": heap.objects, "before": before, "after": after, "freed_later": gc.collect(),
                  "alive": sum(isinstance(o, Node) for o in gc.get_objects()) ,
                  "message": heap.message()}))
"""


def test_a_freeze_takes_start_up_objects_out_of_full_passes_and_later_garbage_is_still_collected() -> None:
    out = subprocess.run(
        [sys.executable, "-c", _CHILD], capture_output=True, text=True, check=True, timeout=60
    )
    r = json.loads(out.stdout)
    assert r["frozen"] >= 20000  # the start-up's objects are in the permanent generation...
    assert r["after"] < 1000 < r["before"]  # ...so the oldest generation a full pass visits is nearly empty
    assert r["freed_later"] >= 1  # a cycle dropped after the freeze is freed
    assert r["alive"] == 0  # gc.get_objects() does not list frozen objects either: none of them visited
    assert r["message"].startswith(f"kept {r['frozen']} start-up objects")


def test_the_freeze_collects_first_so_no_garbage_is_kept_for_ever() -> None:
    calls: list[str] = []

    def collect() -> int:
        calls.append("collect")
        return 0

    heap = freeze_startup_heap(collect=collect, freeze=lambda: calls.append("freeze"), frozen=lambda: 7)
    assert calls == ["collect", "freeze"] and heap.objects == 7
