"""What the core remembers of the samples themselves: the newest one, when each channel and each device last
gave good data (freshness, ``CoreView.data_problems``), and which samples go to the database (decimated).

Owned and driven by the core (``service.core.machine``), one sample at a time; no I/O.
"""

from __future__ import annotations

from collections.abc import Iterable
from datetime import datetime

import numpy as np

from drivers.quality import Quality
from drivers.ringbuffer import Sample
from service.acquire.decimate import SampleDecimator
from service.contracts.columns import finite, finite_list
from service.contracts.records import SampleData
from service.core.view import NewestSample

__all__ = ["SampleBook", "quality_names"]


def quality_names(quality: Iterable[int]) -> tuple[str, ...]:
    """``drivers.quality.Quality`` codes (uint8 or enum) -> "ok", "stale", "open_circuit", ..."""
    names = []
    for q in quality:
        try:
            names.append(Quality(int(q)).name.lower())
        except ValueError:
            names.append(f"unknown_{int(q)}")
    return tuple(names)


class SampleBook:
    """The newest sample, the last good times and the stored-sample decimation (see the module docstring).

    ``min_good_channels``: usable temperature channels (with the ambient) for the DAQ data to count as good;
    ``store_period_s``: one stored sample per this many seconds of sample time.
    """

    def __init__(self, n_channels: int, *, min_good_channels: int, store_period_s: float) -> None:
        self.min_good_channels = min_good_channels
        self.newest: NewestSample | None = None
        self.last_ok_t = np.full(n_channels, np.nan)  # per channel, epoch s of its last OK value
        self.last_good_daq_t: datetime | None = None  # newest sample with enough usable temperatures
        self.last_good_can_t: datetime | None = None  # newest sample with speed and torque from CAN
        self._decimator = SampleDecimator(store_period_s)

    def observe(self, sample: Sample) -> NewestSample:
        """Remember ``sample`` as the newest one (an immutable copy) and update the last good times."""
        temps = np.asarray(sample.temps_c, dtype=float).copy()
        temps.setflags(write=False)
        s = self.newest = NewestSample(
            t=sample.t,
            temps_c=temps,
            quality=quality_names(sample.quality),
            ambient_c=float(sample.ambient_c),
            speed_rpm=float(sample.speed_rpm),
            torque_nm=float(sample.torque_nm),
            can_ok=bool(sample.can_ok),
            daq_ok=bool(sample.daq_ok),
        )
        ok = np.array([q == "ok" for q in s.quality], dtype=bool)[: len(self.last_ok_t)]
        self.last_ok_t[: len(ok)][ok] = sample.t.timestamp()
        usable = int(np.sum(ok & np.isfinite(s.temps_c[: len(ok)])))
        if s.daq_ok and usable >= self.min_good_channels and np.isfinite(s.ambient_c):
            self.last_good_daq_t = s.t
        if s.can_ok and np.isfinite(s.speed_rpm) and np.isfinite(s.torque_nm):
            self.last_good_can_t = s.t
        return s

    def to_store(self, s: NewestSample) -> SampleData | None:
        """The database row of ``s`` if its slot of the decimation grid has none yet, else None."""
        if not self._decimator.keep(s.t.timestamp()):
            return None
        return SampleData(
            t=s.t,
            temps_c=tuple(finite_list(s.temps_c)),
            ambient_c=finite(s.ambient_c),
            speed_rpm=finite(s.speed_rpm),
            torque_nm=finite(s.torque_nm),
            quality=s.quality,
            can_ok=s.can_ok,
            daq_ok=s.daq_ok,
        )
