"""``chtc demo``'s simulated devices and plant run in a child process (issue 30, item 3): the service reads
them through its real drivers (Modbus TCP on loopback, CAN through the python-can-remote hub), the child stops
with the parent, and it never outlives it, even when the parent is killed with SIGKILL."""

from __future__ import annotations

import asyncio
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from service.host.runtime import ScaledClock
from service.settings import Settings
from simulator.rigproc import RigPlan, RigProcess, RigProcessError
from simulator.simrig import make_drivers

# at rest for the whole test (10 plant min at real rate): the speed is 0, the temperatures the first rows';
# one chunk of 20 min, more than AHEAD_S: the child sends nothing more during a test (a broken pipe would end
# it, whatever the guards under test do)
PLAN = {"spindle": None, "seed": 3, "idle_s": 600.0, "segment_s": None, "speedup": 1.0, "chunk_s": 1200.0}


def _refused(host: str, port: int) -> bool:
    try:
        socket.create_connection((host, port), timeout=2.0).close()
    except ConnectionRefusedError:
        return True
    return False


def test_the_demo_rig_serves_from_a_child_process() -> None:
    plan = RigPlan.on_free_ports(**PLAN)

    async def main() -> tuple[object, object, int | None, np.ndarray]:
        rig = RigProcess(plan)
        try:
            rows = await rig.computed()
            await rig.start()
            daq, can_sensor = make_drivers(Settings(), plan.address(), clock=ScaledClock(1.0))
            try:
                temps, status = await daq.read(), await can_sensor.read()
            finally:
                await daq.close()
                await can_sensor.close()
            assert rig.pid != os.getpid() and rig.process.is_alive()
            assert Path(f"/proc/{rig.pid}/comm").read_text().strip() == "chtc-rig"  # named for ps and top
            assert rig.plant_time_s() > 0.0
        finally:
            await rig.stop()
        return temps, status, rig.process.exitcode, rows.temps_c[:2]

    temps, status, code, first_rows = asyncio.run(main())
    assert code == 0  # stopped on request
    assert status.speed_rpm == 0.0 and status.counter in range(16)  # type: ignore[attr-defined]
    read = np.asarray(temps.temps_c)  # type: ignore[attr-defined]
    assert np.all(np.abs(read - first_rows.mean(axis=0)) < 1.0), (read, first_rows)
    # the servers lived in the child: gone with it
    assert _refused(plan.host, plan.modbus_port) and _refused(plan.host, plan.can_port)


def test_a_failing_rig_process_is_a_typed_error_naming_the_cause(tmp_path: Path) -> None:
    plan = RigPlan.on_free_ports(**{**PLAN, "spindle": tmp_path / "missing.toml"})

    async def main() -> None:
        rig = RigProcess(plan)
        try:
            await rig.computed()
        finally:
            await rig.stop()

    with pytest.raises(RigProcessError, match=r"the rig process failed: .*missing\.toml"):
        asyncio.run(main())


CHILD_OF = """
import asyncio, sys
from simulator.rigproc import RigPlan, RigProcess, RigProcessError

async def main():
    plan = RigPlan.on_free_ports(**{plan!r})
    rig = RigProcess(plan)
    await rig.computed()
    await rig.start()
    print(rig.pid, plan.modbus_port, plan.can_port, flush=True)
    await asyncio.Event().wait()

asyncio.run(main())
"""


def _gone(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return True
    return state in ("Z", "X")  # exited (a zombie until its new parent reaps it)


@pytest.mark.skipif(not Path("/proc").is_dir(), reason="reads /proc")
def test_the_rig_process_exits_when_its_parent_is_killed() -> None:
    parent = subprocess.Popen(
        [sys.executable, "-c", CHILD_OF.format(plan=PLAN)],
        stdout=subprocess.PIPE,
        text=True,
        env={**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)},
    )
    try:
        assert parent.stdout is not None
        line = parent.stdout.readline()
        assert line, "the parent printed nothing"
        child, modbus_port, can_port = (int(x) for x in line.split())
        assert not _gone(child)
        os.kill(parent.pid, signal.SIGKILL)
        parent.wait()
        deadline = time.monotonic() + 60.0
        while not _gone(child) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert _gone(child), "the rig process outlived its parent"
        assert _refused("127.0.0.1", modbus_port) and _refused("127.0.0.1", can_port)
    finally:
        if parent.poll() is None:
            parent.kill()
            parent.wait()
