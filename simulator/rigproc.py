"""``chtc demo``'s simulated devices and virtual plant in a child process (issue 30, item 3).

Real devices run beside the soft sensor, not inside it. With the rig in a thread of the service's process
(before), the rig, the plant's chunks and the service shared one GIL: a busy service delayed the devices and
the devices' work delayed the API. Here the rig is a process of its own, as ``chtc simulate`` is: the
simulated Modbus DAQ on a loopback port and the simulated CAN node behind a python-can-remote hub
(``drivers.sim.can_hub``) on another, both chosen by the parent (:meth:`RigPlan.address`), so the service
reaches them exactly as it reaches real devices (Modbus TCP, CAN interface ``remote``). The child computes the
endless plant (``simulator.endless``) chunk by chunk too, ``AHEAD_S`` plant seconds ahead of the time
served.

The parent talks to the child over one ``multiprocessing`` pipe. Child to parent: ``("rows", PlantRows)``
for every chunk (the demo prints the plant's true H from them), ``("ready", t0)`` once serving, where ``t0``
is the child's ``time.monotonic()`` at the timeline's start (``CLOCK_MONOTONIC``: one clock for all processes
of a Linux machine, so :meth:`RigProcess.plant_time_s` needs no round trip), ``("error", text)`` before it
exits on a failure. Parent to child: ``"start"`` (serve from now on: the service is listening), ``"stop"``.

Lifetime: the child is spawned (a fresh interpreter, no forked copy of the service), with SIGINT ignored (a
Ctrl-C in the terminal is the parent's to handle) and one BLAS thread, and named ``chtc-rig``. It never
outlives the parent: it stops when the pipe reaches end of file (the parent exited or was killed, even with
SIGKILL: the kernel closes its end) and, as a second guard, when it is re-parented
(``service.identify.worker.watch_parent``).

Errors::

    RigProcessError(SimulatorError, RuntimeError)   the rig process failed, exited, or did not answer
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import multiprocessing as mp
import os
import signal
import time
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass
from multiprocessing.connection import Connection
from pathlib import Path
from typing import TYPE_CHECKING, Any

from simulator.errors import SimulatorError
from simulator.simrig import SimAddress

if TYPE_CHECKING:
    from drivers.sim.source import TimelineSource
    from simulator.endless import EndlessPlant, PlantRows

__all__ = ["AHEAD_S", "PROCESS_NAME", "RigPlan", "RigProcess", "RigProcessError"]

# the child's name in ps, top and /proc/PID/comm (Linux), so that ``python -m benchmarks api`` tells its CPU
# apart
PROCESS_NAME = "chtc-rig"
# plant seconds computed ahead of the plant time served: a chunk is computed when less than this is left
AHEAD_S = 900.0


class RigProcessError(SimulatorError, RuntimeError):
    """The rig process failed (its message), exited, or did not answer in time."""


@dataclass(frozen=True, kw_only=True)
class RigPlan:
    """What the child serves: the plant (``spindle`` file, ``seed``, ``idle_s`` at rest first, ``segment_s``
    per speed or None for 1–6 min, ``chunk_s`` plant s per chunk), at ``speedup``, on ``host`` with the DAQ
    on ``modbus_port`` and the CAN hub on ``can_port``; the DAQ converts every ``daq_period_s`` plant s."""

    spindle: Path | None
    seed: int
    idle_s: float
    segment_s: float | None
    speedup: float
    host: str
    modbus_port: int
    can_port: int
    chunk_s: float = 1800.0
    daq_period_s: float = 1.0

    @classmethod
    def on_free_ports(cls, **kwargs: Any) -> RigPlan:
        """A plan on free loopback ports (``host`` default 127.0.0.1)."""
        from service.host.runtime import free_port

        host = kwargs.pop("host", "127.0.0.1")
        return cls(host=host, modbus_port=free_port(host), can_port=free_port(host), **kwargs)

    @property
    def can_url(self) -> str:
        return f"ws://{self.host}:{self.can_port}/"

    def address(self) -> SimAddress:
        """Where the service's drivers find the devices (CAN through the hub: interface ``remote``)."""
        return SimAddress(
            host=self.host,
            port=self.modbus_port,
            channel=self.can_url,
            speedup=self.speedup,
            can_interface="remote",
        )


# ------------------------------------------------------------------------------------------ the parent
class RigProcess:
    """The child process serving ``plan``; use on a running event loop.

    ``await computed()`` waits for the plant's first chunk; ``await start()`` makes the child serve it
    (timeline from now on) and waits until it does; ``await stop()`` stops it (idempotent). ``rows`` holds the
    plant rows received so far; :meth:`check` raises the child's failure, if any.
    """

    def __init__(self, plan: RigPlan, *, ready_timeout_s: float = 600.0) -> None:
        from service.identify.worker import single_threaded_children

        self.plan = plan
        self.rows: PlantRows | None = None
        self.ready_timeout_s = ready_timeout_s
        self._t0: float | None = None
        self._failure: str | None = None
        self._changed = asyncio.Event()
        self._loop = asyncio.get_running_loop()
        ctx = mp.get_context("spawn")
        self._conn, child = ctx.Pipe()
        self.process = ctx.Process(
            target=rig_main, args=(child, plan, os.getpid()), name="chtc-rig", daemon=True
        )
        with single_threaded_children():
            self.process.start()
        child.close()  # only the child holds its end: the parent sees EOF when the child exits
        self._loop.add_reader(self._conn.fileno(), self._on_message)

    @property
    def pid(self) -> int | None:
        return self.process.pid

    def plant_time_s(self) -> float:
        """Plant time served now, s (0 before the child started serving)."""
        return 0.0 if self._t0 is None else self.plan.speedup * (time.monotonic() - self._t0)

    def check(self) -> None:
        """Raise ``RigProcessError`` if the child failed or exited."""
        if self._failure is not None:
            raise RigProcessError(self._failure)

    async def computed(self) -> PlantRows:
        """The plant's first chunk (computed by the child)."""
        await self._until(lambda: self.rows is not None, "computed the plant's first chunk")
        assert self.rows is not None
        return self.rows

    async def start(self) -> None:
        """Serve from now on; returns once the devices listen and the plant's timeline runs."""
        self._send("start")
        await self._until(lambda: self._t0 is not None, "started serving")

    async def stop(self, timeout_s: float = 10.0) -> None:
        """Ask the child to stop, wait for it (killed after ``timeout_s``); idempotent."""
        if self._conn.closed:
            return
        with contextlib.suppress(OSError, ValueError):  # the child may be gone already
            self._conn.send("stop")
        await asyncio.to_thread(self.process.join, timeout_s)
        if self.process.is_alive():
            self.process.kill()
            await asyncio.to_thread(self.process.join, timeout_s)
        self._close_conn()

    # --------------------------------------------------------------------------------------- internals
    def _send(self, what: str) -> None:
        self.check()
        self._conn.send(what)

    async def _until(self, done: Callable[[], bool], what: str) -> None:
        deadline = self._loop.time() + self.ready_timeout_s
        while not done():
            self.check()
            self._changed.clear()
            left = deadline - self._loop.time()
            if left <= 0:
                raise RigProcessError(f"the rig process has not {what} within {self.ready_timeout_s:g} s")
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._changed.wait(), left)

    def _on_message(self) -> None:
        try:
            kind, body = self._conn.recv()
        except (EOFError, OSError):
            self._close_conn()
            self.process.join(1.0)
            code = self.process.exitcode
            self._failure = self._failure or f"the rig process exited (code {code})"
        else:
            if kind == "rows":
                self.rows = body if self.rows is None else self.rows + body
            elif kind == "ready":
                self._t0 = float(body)
            elif kind == "error":
                self._failure = f"the rig process failed: {body}"
        self._changed.set()

    def _close_conn(self) -> None:
        if not self._conn.closed:
            with contextlib.suppress(ValueError, OSError):
                self._loop.remove_reader(self._conn.fileno())
            self._conn.close()


# ------------------------------------------------------------------------------------------- the child
def rig_main(conn: Connection, plan: RigPlan, parent_pid: int) -> None:
    """The child's entry point: serve ``plan`` until told to stop or the parent is gone."""
    from service.identify.worker import watch_parent

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    name_process(PROCESS_NAME)
    watch_parent(parent_pid)
    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)  # the service's drivers report their errors
    try:
        asyncio.run(_serve(conn, plan))
    except Exception as err:  # anything the rig hits is reported to the parent, which stops the demo
        with contextlib.suppress(OSError, ValueError):
            conn.send(("error", f"{type(err).__name__}: {err}"))
        raise SystemExit(1) from err


def name_process(name: str) -> None:
    """Set this process's name as ``ps`` and ``/proc/PID/comm`` show it (Linux ``prctl(PR_SET_NAME)``; a
    no-op where it is not available)."""
    import ctypes
    import ctypes.util

    with contextlib.suppress(OSError, AttributeError, TypeError):
        libc = ctypes.CDLL(ctypes.util.find_library("c"), use_errno=True)
        libc.prctl(15, name.encode()[:15], 0, 0, 0)  # 15: PR_SET_NAME


class _Inbox:
    """The parent's commands, read on the child's loop: ``start`` and ``stop`` (end of file is a stop)."""

    def __init__(self, conn: Connection) -> None:
        self.conn = conn
        self.start, self.stop = asyncio.Event(), asyncio.Event()
        asyncio.get_running_loop().add_reader(conn.fileno(), self._read)

    def _read(self) -> None:
        try:
            what = self.conn.recv()
        except (EOFError, OSError):
            asyncio.get_running_loop().remove_reader(self.conn.fileno())
            what = "stop"  # the parent is gone
        (self.start if what == "start" else self.stop).set()


async def _serve(conn: Connection, plan: RigPlan) -> None:
    from model.geometry import load_spindle
    from simulator.endless import EndlessPlant

    inbox = _Inbox(conn)
    plant = EndlessPlant(
        load_spindle(plan.spindle),
        seed=plan.seed,
        idle_s=plan.idle_s,
        segment_s=plan.segment_s,
        chunk_s=plan.chunk_s,
    )
    first = await asyncio.to_thread(plant.next_chunk)
    plant.append(first)
    conn.send(("rows", first))
    await _first(inbox.start, inbox.stop)
    if inbox.stop.is_set():
        return
    async with _devices(plant, plan) as source:
        conn.send(("ready", time.monotonic() - source.wall_elapsed_s()))
        await _keep_ahead(plant, source, conn, inbox.stop)


async def _first(*events: asyncio.Event) -> None:
    waits = [asyncio.ensure_future(e.wait()) for e in events]
    try:
        await asyncio.wait(waits, return_when=asyncio.FIRST_COMPLETED)
    finally:
        for w in waits:
            w.cancel()


@contextlib.asynccontextmanager
async def _devices(plant: EndlessPlant, plan: RigPlan) -> AsyncIterator[TimelineSource]:
    """The DAQ and the CAN node (behind the hub) playing the plant's rows from now on; yields the source."""
    import can

    from drivers.sim.can_hub import CanHub
    from drivers.sim.can_node import SimulatedCanNode
    from drivers.sim.modbus_server import SimulatedDaq
    from drivers.sim.source import TimelineSource

    assert plant.rows is not None
    channel = f"chtc-rig-{os.getpid()}"
    hub = CanHub(plan.can_url, channel)
    hub.start()
    bus = can.Bus(interface="virtual", channel=channel, ignore_config=True)
    source = TimelineSource(plant.rows, speedup=plan.speedup)
    daq = SimulatedDaq(
        source, host=plan.host, port=plan.modbus_port, sample_period_s=plan.daq_period_s / plan.speedup
    )
    node = SimulatedCanNode(source, bus=bus)
    try:
        source.start()
        await daq.start()
        await node.start()
        yield source
    finally:
        await node.stop()
        await daq.stop()
        bus.shutdown()
        await asyncio.to_thread(hub.stop)


async def _keep_ahead(
    plant: EndlessPlant, source: TimelineSource, conn: Connection, stop: asyncio.Event
) -> None:
    """Compute the plant's next chunk (in a thread) whenever less than ``AHEAD_S`` plant seconds are left
    ahead of the time served; the devices play it, the parent gets its rows."""
    while not stop.is_set():
        if plant.end_s - (source.sim_time_s() - float(source.run.times_s[0])) < AHEAD_S:
            chunk = await asyncio.to_thread(plant.next_chunk)
            plant.append(chunk)
            source.extend(chunk)
            conn.send(("rows", chunk))
            continue
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(stop.wait(), timeout=0.5)
