"""Replay a recorded pair (temperature CSV + CAN log) through the simulated devices.

Both logs carry absolute UTC times. The replay fixes one reference ``t_ref`` (the earlier of the first CSV
row and the first CAN frame) and maps a recorded time ``t`` to the wall time ``start + (t - t_ref) / speed``:

- the DAQ (:class:`~drivers.sim.modbus_server.SimulatedDaq`) serves the CSV row recorded at or before the
  current replay time (``TimelineSource`` in ``hold`` mode, so values are the recorded ones exactly, status
  included);
- the CAN frames go onto the bus through ``can.MessageSync`` (``timestamps=True``) fed with copies whose
  timestamps are scaled by ``1/speed``; it sleeps until each frame is due. Gaps longer than ``skip_s`` (wall)
  are shortened to ``skip_s``, as MessageSync does.

``MessageSync`` blocks, so the CAN side runs in a worker thread; stopping sets an event that the thread
checks before every frame (a stop is seen within one inter-frame gap).
"""

from __future__ import annotations

import asyncio
import contextlib
import threading
import time
from collections.abc import Iterator, Sequence
from pathlib import Path
from types import TracebackType

import can
import numpy as np

from drivers.logs import TemperatureLog, read_can_log, read_temperature_csv
from drivers.registers import RegisterMap
from drivers.sim.faults import FaultController
from drivers.sim.modbus_server import SimulatedDaq
from drivers.sim.source import ArrayTimeline, Clock, TimelineSource

__all__ = ["CanReplayer", "Replay", "timeline_from_log"]


def timeline_from_log(log: TemperatureLog, *, t_ref: float | None = None) -> tuple[ArrayTimeline, list[int]]:
    """A timeline from a temperature log, times in s after ``t_ref`` (POSIX s; default the first row), and
    the recorded DAQ counter of each timeline row (-1 where unknown).

    If ``t_ref`` is earlier than the first row, that row is also shown from ``t_ref`` on. Speed and torque
    are zero (they come from the CAN log).
    """
    ref = float(log.t_s[0]) if t_ref is None else t_ref
    times = log.t_s - ref
    temps, ambient, status, counter = log.temps_c, log.ambient_c, log.status, log.counter
    if times[0] > 0:
        times = np.concatenate([[0.0], times])
        temps, ambient, status, counter = (
            np.concatenate([a[:1], a]) for a in (temps, ambient, status, counter)
        )
    times = _strictly_increasing(times)
    zeros = np.zeros(times.size)
    timeline = ArrayTimeline(times, temps, ambient, zeros, zeros.copy(), status.astype(np.int64))
    return timeline, [int(c) for c in counter]


def _strictly_increasing(times: np.ndarray) -> np.ndarray:
    """Rows with equal timestamps are nudged 1 µs apart (the later one wins in hold mode)."""
    out = np.array(times, dtype=float)
    for i in range(1, out.size):
        if out[i] <= out[i - 1]:
            out[i] = out[i - 1] + 1e-6
    return out


class CanReplayer:
    """Sends recorded frames on ``bus`` at their recorded pace divided by ``speed`` (MessageSync, a thread).

    ``t_ref`` (POSIX s) is the recorded instant that maps to :meth:`start`; frames recorded before it are
    sent at once. ``done`` is set when the last frame has gone or the replayer was stopped.
    """

    def __init__(
        self,
        messages: Sequence[can.Message],
        *,
        bus: can.BusABC,
        speed: float = 1.0,
        t_ref: float | None = None,
        skip_s: float = 60.0,
    ) -> None:
        if not speed > 0:
            raise ValueError(f"speed: must be > 0, got {speed}")
        self.messages = list(messages)
        self.bus = bus
        self.speed = speed
        self.t_ref = t_ref if t_ref is not None else (self.messages[0].timestamp if self.messages else 0.0)
        self.skip_s = skip_s
        self.frames_sent = 0
        self.done = threading.Event()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.error: BaseException | None = None

    def _scaled(self) -> Iterator[can.Message]:
        for msg in self.messages:
            t = self.t_ref + (msg.timestamp - self.t_ref) / self.speed
            yield can.Message(
                timestamp=t,
                arbitration_id=msg.arbitration_id,
                is_extended_id=msg.is_extended_id,
                is_remote_frame=msg.is_remote_frame,
                is_error_frame=msg.is_error_frame,
                is_fd=msg.is_fd,
                bitrate_switch=msg.bitrate_switch,
                dlc=msg.dlc,
                data=msg.data,
                check=False,
            )

    def _run(self) -> None:
        try:
            first = self.messages[0].timestamp if self.messages else self.t_ref
            if self._stop.wait(max(0.0, (first - self.t_ref) / self.speed)):
                return
            for msg in can.MessageSync(self._scaled(), timestamps=True, skip=self.skip_s):
                if self._stop.is_set():
                    return
                self.bus.send(msg)
                self.frames_sent += 1
        except can.CanError as err:
            self.error = err
        finally:
            self.done.set()

    def start(self) -> None:
        """Start sending in a daemon thread."""
        self._thread = threading.Thread(target=self._run, name="can-replay", daemon=True)
        self._thread.start()

    def stop(self, timeout: float = 1.0) -> None:
        """Ask the thread to stop and wait up to ``timeout`` s for it."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout)


class Replay:
    """A recorded CSV + CAN log served by a simulated DAQ and sent on a bus; an async context manager."""

    def __init__(
        self,
        csv_path: str | Path,
        can_path: str | Path | None,
        *,
        bus: can.BusABC | None,
        speed: float = 1.0,
        host: str = "127.0.0.1",
        port: int = 5020,
        register_map: RegisterMap | None = None,
        faults: FaultController | None = None,
        clock: Clock | None = None,
    ) -> None:
        self.log = read_temperature_csv(csv_path)
        self.frames = read_can_log(can_path) if can_path is not None else []
        firsts = [float(self.log.t_s[0])] + ([self.frames[0].timestamp] if self.frames else [])
        self.t_ref = min(firsts)
        timeline, counters = timeline_from_log(self.log, t_ref=self.t_ref)
        self.source = TimelineSource(timeline, speedup=speed, mode="hold", clock=clock or time.monotonic)
        self.daq = SimulatedDaq(
            self.source,
            host=host,
            port=port,
            register_map=register_map,
            faults=faults,
            sampling="row",
            row_counters=counters,
        )
        self.can: CanReplayer | None = None
        if bus is not None and self.frames:
            self.can = CanReplayer(self.frames, bus=bus, speed=speed, t_ref=self.t_ref)

    @property
    def duration_s(self) -> float:
        """Wall seconds the replay takes (the later of the two logs' ends)."""
        last = max([float(self.log.t_s[-1])] + ([self.frames[-1].timestamp] if self.frames else []))
        return (last - self.t_ref) / self.source.speedup

    async def listen(self) -> None:
        """Bind the DAQ's port (it serves the first row until :meth:`begin`)."""
        await self.daq.start()

    def begin(self) -> None:
        """Start the replay clock and the CAN frames at the same instant."""
        self.source.start()
        if self.can is not None:
            self.can.start()

    async def start(self) -> None:
        """:meth:`listen` then :meth:`begin`."""
        await self.listen()
        self.begin()

    async def stop(self) -> None:
        """Stop the CAN thread and the DAQ."""
        if self.can is not None:
            await asyncio.to_thread(self.can.stop)
        with contextlib.suppress(Exception):
            await self.daq.stop()

    async def __aenter__(self) -> Replay:
        await self.start()
        return self

    async def __aexit__(
        self, et: type[BaseException] | None, ev: BaseException | None, tb: TracebackType | None
    ) -> None:
        await self.stop()
