"""Simulated speed/torque sensor: sends ``SpindleStatus`` frames from a timeline on any python-can bus.

The real sensor sends every 10 ms. At a speed-up ``S`` that would be one frame per ``10/S`` ms of wall time,
which no bus in this project needs; the node sends one frame per ``max(sim_period_s / S, min_wall_period_s)``
wall seconds (10 ms at any speed-up >= 1) carrying the values at the current simulated time, with the 4-bit
rolling counter advancing by one per frame. The bus is injected (``virtual`` in process, ``remote`` across
processes, ``socketcan`` in production); the node never creates or shuts it down.

Faults (``drivers.sim.faults``): ``silence`` sends nothing, ``counter-gap`` skips the counter once per
activation, ``unknown-id`` adds a frame with a foreign ID each period, ``wrong-dlc`` sends the wrong length,
``fault-status`` sets the status byte (2 fault, 1 warning, anything else is invalid), ``fd`` sends
``SpindleStatus`` as a CAN FD frame, ``extended-id`` with a 29-bit ID 0x181, ``remote`` adds a remote frame
0x181 each period. Frames sent under a fault still advance the rolling counter, as a real sensor's would.

Errors: ``drivers.errors.DeviceUnavailableError`` when the bus refuses a frame.
"""

from __future__ import annotations

import asyncio
import contextlib
from types import TracebackType

import can
import numpy as np

from drivers.can_codec import COUNTER_MODULO, SPINDLE_STATUS_ID, encode_status
from drivers.errors import DeviceUnavailableError
from drivers.sim.faults import FaultController, FaultKind
from drivers.sim.source import TimelineSource

__all__ = ["SimulatedCanNode"]

_SPEED_MAX_RPM = 65535.0
_TORQUE_MAX_NM = 327.67


class SimulatedCanNode:
    """Sends ``SpindleStatus`` from ``source`` on ``bus``; use as an async context manager."""

    def __init__(
        self,
        source: TimelineSource,
        *,
        bus: can.BusABC,
        faults: FaultController | None = None,
        sim_period_s: float = 0.010,
        min_wall_period_s: float = 0.010,
        status: int = 0,
    ) -> None:
        self.source = source
        self.bus = bus
        self.faults = faults or FaultController(clock=source.clock)
        self.period_s = max(sim_period_s / source.speedup, min_wall_period_s)
        self.status = status
        self.counter = 0
        self.frames_sent = 0
        self.send_errors = 0
        self._task: asyncio.Task[None] | None = None

    async def start(self) -> None:
        """Start sending (the timeline and the fault schedule start now if they have not already)."""
        self.source.wall_elapsed_s()
        self.faults.start()
        self._task = asyncio.create_task(self._run(), name="sim-can-node")

    async def stop(self) -> None:
        """Stop sending (the bus stays open: it belongs to the caller)."""
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task
            self._task = None

    async def __aenter__(self) -> SimulatedCanNode:
        await self.start()
        return self

    async def __aexit__(
        self, et: type[BaseException] | None, ev: BaseException | None, tb: TracebackType | None
    ) -> None:
        await self.stop()

    async def _run(self) -> None:
        loop = asyncio.get_running_loop()
        next_t = loop.time()
        while True:
            try:
                self.send_once()
            except DeviceUnavailableError:
                self.send_errors += 1
            next_t += self.period_s
            delay = next_t - loop.time()
            if delay < -self.period_s:  # fell behind (busy machine): resynchronise instead of bursting
                next_t, delay = loop.time(), 0.0
            await asyncio.sleep(max(delay, 0.0))

    def frames(self) -> list[can.Message]:
        """The frames one period produces now (advances the counter); pure apart from counter and faults."""
        if self.faults.is_active(FaultKind.SILENCE):
            return []
        gap = self.faults.take_once(FaultKind.COUNTER_GAP)
        if gap is not None:
            self.counter = (self.counter + int(gap.param())) % COUNTER_MODULO
        out = [self._status_frame()]
        self.counter = (self.counter + 1) % COUNTER_MODULO
        if self.faults.is_active(FaultKind.REMOTE_FRAME):
            out.append(
                can.Message(
                    arbitration_id=SPINDLE_STATUS_ID, is_extended_id=False, is_remote_frame=True, dlc=6
                )
            )
        foreign = self.faults.first(FaultKind.UNKNOWN_ID)
        if foreign is not None:
            out.append(can.Message(arbitration_id=int(foreign.param()), is_extended_id=False, data=bytes(8)))
        return out

    def _status_frame(self) -> can.Message:
        snap = self.source.now()
        status = self.status
        fault_status = self.faults.first(FaultKind.FAULT_STATUS)
        if fault_status is not None:
            status = int(fault_status.param())
        speed = float(np.clip(round(snap.speed_rpm), 0.0, _SPEED_MAX_RPM))
        torque = float(np.clip(round(snap.torque_nm, 2), -_TORQUE_MAX_NM, _TORQUE_MAX_NM))
        data = encode_status(speed, torque, self.counter, status)
        wrong = self.faults.first(FaultKind.WRONG_DLC)
        if wrong is not None:
            dlc = int(wrong.param())
            data = (data + bytes(8))[:dlc]
        return can.Message(
            arbitration_id=SPINDLE_STATUS_ID,
            is_extended_id=self.faults.is_active(FaultKind.EXTENDED_ID),
            is_fd=self.faults.is_active(FaultKind.FD_FRAME),
            data=data,
        )

    def send_once(self) -> int:
        """Send one period's frames now; returns how many were sent."""
        frames = self.frames()
        for msg in frames:
            try:
                self.bus.send(msg)
            except can.CanError as err:
                raise DeviceUnavailableError(
                    f"send failed: {err}", device=f"sim-can {self.bus.channel_info}"
                ) from err
        self.frames_sent += len(frames)
        return len(frames)
