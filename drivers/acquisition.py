"""Combine the latest DAQ reading and CAN status into one ``Sample`` per period and store it in a ring buffer.

``Acquisition.sample()`` is the pure-ish step (reads the drivers' ``current()``, appends, returns the sample);
``run_sampler()`` calls it every ``period_s`` on the injected clock; ``run()`` also runs both drivers' poll
loops. Rules for the combined sample:

- no DAQ reading yet → temperatures NaN, quality ``NO_DATA``, ``daq_ok=False``;
- DAQ stale (silent, or its sample counter frozen) → last values, quality ``STALE``, ``daq_ok=False``;
- ambient flagged by the DAQ (open circuit, NaN, out of range, stale) → ``ambient_c`` NaN;
- no CAN frame yet → speed/torque NaN, ``can_ok=False``; stale or sensor fault → last values,
  ``can_ok=False``; a sensor warning keeps ``can_ok=True`` (it is counted by the CAN driver).
"""

from __future__ import annotations

import asyncio
import math
import time
from collections.abc import Callable
from datetime import datetime
from typing import Protocol

import numpy as np

from drivers.base import Clock, Sleep, WallClock, utc_now
from drivers.can_sensor import CanReading
from drivers.errors import NoDataError
from drivers.modbus_daq import DaqReading
from drivers.quality import Quality
from drivers.ringbuffer import RingBuffer, Sample


class DaqSource(Protocol):
    """What the sampler needs from the DAQ driver (``ModbusDaq`` satisfies it)."""

    def current(self) -> DaqReading: ...

    async def run(self, *, interval_s: float) -> None: ...


class CanSource(Protocol):
    """What the sampler needs from the CAN driver (``CanSpindleSensor`` satisfies it)."""

    def current(self) -> CanReading: ...

    async def run(self, *, interval_s: float) -> None: ...


def combine(daq: DaqReading | None, can: CanReading | None, *, t: datetime, n_channels: int) -> Sample:
    """One ``Sample`` at ``t`` (UTC) from the drivers' current readings (``None``: nothing received yet)."""
    if daq is None:
        temps = np.full(n_channels, np.nan)
        quality = np.full(n_channels, np.uint8(Quality.NO_DATA))
        ambient, daq_ok = math.nan, False
    else:
        temps, quality = daq.temps_c.copy(), daq.quality.copy()
        ambient = daq.ambient_c if daq.ambient_quality is Quality.OK else math.nan
        daq_ok = not bool(np.all(quality == np.uint8(Quality.STALE)))
    if can is None:
        speed, torque, can_ok = math.nan, math.nan, False
    else:
        speed, torque, can_ok = can.speed_rpm, can.torque_nm, can.quality is Quality.OK
    return Sample(t, temps, ambient, speed, torque, quality, daq_ok=daq_ok, can_ok=can_ok)


class Acquisition:
    """Samples ``daq`` and ``can`` every ``period_s`` seconds into ``ring``.

    ``on_sample`` (optional) is called with each stored sample (e.g. the condition detector or a DB writer).
    """

    def __init__(
        self,
        daq: DaqSource,
        can: CanSource,
        ring: RingBuffer,
        *,
        period_s: float = 10.0,
        on_sample: Callable[[Sample], None] | None = None,
        clock: Clock = time.monotonic,
        now: WallClock = utc_now,
        sleep: Sleep = asyncio.sleep,
    ) -> None:
        if period_s <= 0:
            raise ValueError(f"period_s must be > 0, got {period_s}")
        self.daq, self.can, self.ring = daq, can, ring
        self.period_s = period_s
        self.on_sample = on_sample
        self._clock, self._now, self._sleep = clock, now, sleep
        self.samples = 0

    def sample(self) -> Sample:
        """Build the current sample, append it to the ring buffer and return it."""
        try:
            daq: DaqReading | None = self.daq.current()
        except NoDataError:
            daq = None
        try:
            can: CanReading | None = self.can.current()
        except NoDataError:
            can = None
        s = combine(daq, can, t=self._now(), n_channels=self.ring.n_channels)
        self.ring.append(s)
        self.samples += 1
        if self.on_sample is not None:
            self.on_sample(s)
        return s

    async def run_sampler(self) -> None:
        """Call ``sample()`` every ``period_s`` (on the injected clock, without drift) until cancelled.

        If the loop falls more than one period behind it skips the missed ticks instead of bursting, and keeps
        the phase of the ticks (a replay relies on it: ``chtc replay`` starts the log in phase with them)."""
        next_tick = self._clock() + self.period_s
        while True:
            await self._sleep(max(0.0, next_tick - self._clock()))
            self.sample()
            next_tick += self.period_s
            behind = self._clock() - next_tick
            if behind > 0:
                next_tick += math.ceil(behind / self.period_s) * self.period_s

    async def run(self, *, poll_interval_s: float = 1.0) -> None:
        """Run the DAQ poll loop, the CAN receive loop and the sampler together until cancelled."""
        async with asyncio.TaskGroup() as tg:
            tg.create_task(self.daq.run(interval_s=poll_interval_s))
            tg.create_task(self.can.run(interval_s=0.0))
            tg.create_task(self.run_sampler())
