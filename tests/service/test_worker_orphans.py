"""Issue 13.5: a kill -9 of the service leaves no process behind (the identification worker notices its
parent's death and exits; multiprocessing's resource tracker then sees EOF and exits too)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]

SERVICE = textwrap.dedent(
    """
    import asyncio, os
    from service.modelload import ModelRef
    from service.settings import Settings
    from service.identify.worker import IdentificationWorker

    async def main():
        worker = IdentificationWorker(ModelRef.from_settings(Settings()))
        await worker.start()
        print("ready", flush=True)
        await asyncio.sleep(3600)

    asyncio.run(main())
    """
)


def _children() -> dict[int, list[int]]:
    out: dict[int, list[int]] = {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
        except OSError:
            continue
        ppid = int(stat.rsplit(")", 1)[1].split()[1])
        out.setdefault(ppid, []).append(int(entry.name))
    return out


def descendants(pid: int) -> set[int]:
    tree = _children()
    found: set[int] = set()
    todo = [pid]
    while todo:
        for child in tree.get(todo.pop(), []):
            if child not in found:
                found.add(child)
                todo.append(child)
    return found


def alive(pid: int) -> bool:
    """Running (a zombie waiting for a reaper that never comes counts as gone)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat.rsplit(")", 1)[1].split()[0] != "Z"


@pytest.mark.skipif(not Path("/proc").is_dir(), reason="needs /proc")
def test_kill_9_of_the_service_leaves_no_process_behind(loaded_model) -> None:
    del loaded_model  # the reduced-model cache exists, so the worker starts in about a second
    proc = subprocess.Popen(
        [sys.executable, "-c", SERVICE], cwd=REPO, stdout=subprocess.PIPE, text=True, env={**os.environ}
    )
    try:
        assert proc.stdout is not None
        assert proc.stdout.readline().strip() == "ready"
        left = descendants(proc.pid)
        assert len(left) >= 2  # the worker and the resource tracker
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(timeout=10)
        deadline = time.monotonic() + 10.0
        while any(alive(p) for p in left) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert [p for p in left if alive(p)] == []
    finally:
        if proc.poll() is None:
            proc.kill()


def test_worker_runs_at_a_lower_priority(model_ref) -> None:
    """The identification process is niced (WORKER_NICE) so /chtc keeps its latency during identification."""
    import asyncio

    from service.identify.worker import WORKER_NICE, IdentificationWorker

    async def nice_of_worker() -> list[int]:
        worker = IdentificationWorker(model_ref)
        try:
            await worker.start()
            return [os.getpriority(os.PRIO_PROCESS, pid) for pid in worker.pids()]
        finally:
            worker.close()

    mine = os.getpriority(os.PRIO_PROCESS, 0)
    assert asyncio.run(nice_of_worker()) == [min(19, mine + WORKER_NICE)]
