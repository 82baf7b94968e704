"""The immutable snapshot of the service core that the outlets (REST, OPC UA, MQTT) read: :class:`CoreView`.

The shell publishes one after each event it handled (``ServiceCore.view()``) by swapping a reference, so a
reader takes no lock and always sees one consistent state. Everything in it is frozen: tuples, read-only
numpy arrays, ``MappingProxyType`` copies and frozen dataclasses. Ages and data problems are computed from it
at the reader's ``now`` (the data go stale while no event arrives).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from datetime import datetime

import numpy as np

from service.contracts.calibration import Calibration
from service.contracts.metrics import HistogramData
from service.contracts.snapshots import ConditionSnapshot, IdentificationJob, IdentificationRecord
from service.contracts.verdict import DataCode, DataProblem
from service.estimate.state import FilterView
from service.identify.speedmap import MapConfig, SpeedMap

__all__ = ["CoreView", "NewestSample"]


@dataclass(frozen=True, eq=False, kw_only=True)
class NewestSample:
    """The newest acquisition sample: t UTC; temps_c (n,) °C read-only; quality names per channel."""

    t: datetime
    temps_c: np.ndarray
    quality: tuple[str, ...]
    ambient_c: float
    speed_rpm: float
    torque_nm: float
    can_ok: bool
    daq_ok: bool


@dataclass(frozen=True, eq=False, kw_only=True)
class CoreView:
    """What the core knows after one event (see the module docstring)."""

    newest: NewestSample | None
    condition: ConditionSnapshot | None
    conditions: tuple[ConditionSnapshot, ...]  # newest first
    current: IdentificationRecord | None  # the newest ok identification (or the restored one)
    current_from_restore: bool  # ``current`` is the stored one, not re-identified since the restart
    records: tuple[IdentificationRecord, ...]  # this process's identifications, newest first
    jobs: Mapping[str, IdentificationJob]
    running_job: str | None  # key of the job the scheduler waits for
    counts: Mapping[str, int]  # identifications by outcome
    durations: HistogramData  # worker wall time per job, s
    last_ok_t: tuple[float, ...]  # per channel, epoch s of its last OK value (NaN: never)
    last_good_daq_t: datetime | None  # newest sample with enough usable temperatures and the ambient
    last_good_can_t: datetime | None  # newest sample with speed and torque from CAN
    calibration: Calibration | None  # the current offset baseline (None: none, or calibration off)
    offset_sd_c: np.ndarray | None  # (n,) °C 1σ of the offsets still unknown (None: calibration off)
    live: FilterView | None  # the filtered live state (None before it started)
    stale_after_s: float
    min_good_channels: int
    # speed-map and combined mode (docs/design/hmap.md): the map's configuration (None: no map in this mode)
    # and the latest map fit
    map_config: MapConfig | None = None
    speed_map: SpeedMap | None = None
    # the serving strategy's verdict (service.core.serving): ``current`` is the map's fit and /chtc serves H
    # from the map at the current speed; false in per-condition mode, and in combined mode while the held
    # condition's per-condition identification serves (docs/design/hmap.md, "Combined mode")
    map_serves: bool = True
    ci_threshold: float = 0.5  # identification.ci_rel_threshold (the core's config)
    # the baseline in use is the commissioning's and its check against the live residuals has not ended yet
    # (``service.core.baselinecheck``): not a founded baseline for the verdict until it has
    offsets_unchecked: bool = False
    h_form_sd: float = 0.0  # experimental.h_form_sd_ln: 1σ in ln H added to every served H band
    # the core thread's backlog (service.shell.corethread; the shell sets both when it publishes): the time
    # stamp of the oldest sample acquired but not handled yet (None: none waits), and how old it may get
    # before the data are not fresh (``core_behind``)
    pending_since: datetime | None = None
    max_core_lag_s: float = math.inf

    def data_problems(self, now: datetime) -> tuple[DataProblem, ...]:
        """Why the data are not fresh at ``now`` (empty: fresh). Codes (``DataCode``): ``no_sample`` (nothing
        acquired for ``stale_after_s``: acquisition stalled), ``daq_no_good_data`` (no sample with
        ``min_good_channels`` usable channels and the ambient for that long: DAQ unreachable, hung, garbled,
        frozen or channels broken), ``can_no_good_data`` (no speed/torque from CAN: silent, fault),
        ``core_behind`` (a sample acquired ``max_core_lag_s`` ago still waits for the core: what this view
        holds trails what was acquired)."""
        limit = self.stale_after_s
        behind = self.core_lag_s(now)
        lag = (
            [
                DataProblem(
                    DataCode.CORE_BEHIND,
                    f"samples wait {behind:.1f} s for the core (limit {self.max_core_lag_s:g} s)",
                )
            ]
            if behind > self.max_core_lag_s
            else []
        )
        if self.newest is None:
            return (DataProblem(DataCode.NO_SAMPLE, "no sample acquired yet"), *lag)
        out = lag
        age = (now - self.newest.t).total_seconds()
        if age > limit:
            out.append(
                DataProblem(DataCode.NO_SAMPLE, f"newest sample {age:.0f} s old (limit {limit:.0f} s)")
            )
        n = self.min_good_channels
        what = f"sample with >= {n} usable temperature channels and the ambient"
        out += _age_problem(
            DataCode.DAQ_NO_GOOD_DATA, what=what, last=self.last_good_daq_t, now=now, limit_s=limit
        )
        can = "speed and torque from CAN"
        out += _age_problem(
            DataCode.CAN_NO_GOOD_DATA, what=can, last=self.last_good_can_t, now=now, limit_s=limit
        )
        return tuple(out)

    def core_lag_s(self, now: datetime) -> float:
        """How long the oldest sample not yet handled by the core has waited at ``now`` [s] (0: none)."""
        if self.pending_since is None:
            return 0.0
        return max(0.0, (now - self.pending_since).total_seconds())

    def channel_ages(self, now: datetime) -> list[float | None]:
        """Seconds since each channel's last OK value (None: never)."""
        ts = now.timestamp()
        return [None if not np.isfinite(t) else max(0.0, ts - float(t)) for t in self.last_ok_t]


def _age_problem(
    code: DataCode, *, what: str, last: datetime | None, now: datetime, limit_s: float
) -> list[DataProblem]:
    if last is None:
        return [DataProblem(code, f"no {what} yet")]
    age = (now - last).total_seconds()
    return (
        [DataProblem(code, f"newest {what} is {age:.1f} s old (limit {limit_s:.0f} s)")]
        if age > limit_s
        else []
    )
