"""An in-memory :class:`service.serve.interface.ChtcService` for API tests, the API benchmark and dashboard
work.

It holds the same state the running service does (newest sample, identifications, jobs, device health) and
derives the same statuses from it, but everything is driven explicitly: ``add_sample()``,
``add_identification()``, ``finish_job()``, ``set_device()``. Time comes from an injected ``clock``.

The section mesh is the real FE mesh when ``model`` is importable (:func:`model_section`) or a synthetic
spindle-like (r, z) section (:func:`synthetic_section`) otherwise; the "predicted" field is a smooth analytic
function of H and the condition (bearing hot spots decaying with H), not a FE solution.
"""

from __future__ import annotations

import itertools
import threading
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from datetime import UTC, datetime, timedelta

import numpy as np

from service.serve.histogram import DURATION_BUCKETS_S, LATENCY_BUCKETS_S, Histogram
from service.serve.interface import (
    BusyError,
    ChtcSnapshot,
    ChtcStatus,
    CompensationSnapshot,
    ConditionSnapshot,
    ConditionState,
    DeviceHealth,
    DeviceStatus,
    FieldAt,
    FieldSnapshot,
    HealthSnapshot,
    IdentificationJob,
    IdentificationPage,
    IdentificationRecord,
    JobState,
    MetricsSnapshot,
    NoDataYetError,
    NotFoundError,
    NotReadyError,
    OffsetBaseline,
    Readiness,
    SectionPart,
    SensorHistory,
    SensorHistoryBuffer,
    SensorReading,
    SpindleLayout,
    ZoneInfo,
)
from service.serve.views import chtc_snapshot, data_to_record
from service.store.records import IdentificationData

MIN_GOOD_CHANNELS = 24  # identification.min_good_channels' default

Clock = Callable[[], datetime]


def utc_now() -> datetime:
    return datetime.now(UTC)


SteadySolver = Callable[[np.ndarray, ConditionSnapshot], np.ndarray]


@dataclass(frozen=True, eq=False)
class Section:
    """An (r, z) section mesh, the 32 sensor positions on it and how to get a steady field (°C) on it."""

    nodes_rz: np.ndarray  # (N, 2) m
    triangles: np.ndarray  # (M, 3)
    sensors: Sequence[tuple[int, str, str, float, float]]  # (channel, name, role, r_m, z_m)
    model_version: str
    steady: SteadySolver | None = None  # None: the analytic stand-in (analytic_field)
    parts: tuple[SectionPart, ...] = ()  # named solid parts (for labels); () = unnamed
    zones: tuple[ZoneInfo, ...] = ()


_PART_NAMES = ("shaft", "front_bearing", "rear_bearing", "housing", "pulley")
_ZONE_TEXT = (  # SPEC §2
    "rear shaft pulley <-> ambient air",
    "right end face of the rear bearing <-> air gap",
    "intermediate bearing <-> air gap",
    "left end face of the rear bearing <-> air gap",
    "front shaft shoulder <-> ambient air",
    "housing <-> air gap",
    "housing <-> ambient air",
)


# Synthetic spindle: (r0, r1, z0, z1) rectangles in m: shaft, front/rear bearings, housing, pulley.
_PARTS = (
    (0.0, 0.035, 0.0, 0.50),
    (0.035, 0.060, 0.06, 0.12),
    (0.035, 0.060, 0.34, 0.38),
    (0.060, 0.110, 0.04, 0.42),
    (0.0, 0.055, 0.50, 0.56),
)
_FRONT_Z, _REAR_Z, _BEARING_R = 0.09, 0.36, 0.0475


def synthetic_section(*, nr: int = 45, nz: int = 113) -> Section:
    """A structured triangulation of a spindle-like union of rectangles; 12 bearing + 20 housing sensors."""
    r = np.linspace(0.0, 0.110, nr)
    z = np.linspace(0.0, 0.56, nz)
    rr, zz = np.meshgrid(r, z, indexing="ij")
    nodes = np.c_[rr.ravel(), zz.ravel()]
    idx = np.arange(nr * nz).reshape(nr, nz)
    a, b, c, d = idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]
    cr = (r[:-1, None] + r[1:, None]) / 2 + 0 * z[None, :-1]
    cz = 0 * r[:-1, None] + (z[None, :-1] + z[None, 1:]) / 2
    keep = np.zeros_like(cr, dtype=bool)
    for r0, r1, z0, z1 in _PARTS:
        keep |= (cr >= r0) & (cr <= r1) & (cz >= z0) & (cz <= z1)
    tris = np.concatenate([np.c_[a[keep], b[keep], c[keep]], np.c_[a[keep], c[keep], d[keep]]])
    used = np.unique(tris)
    remap = np.full(len(nodes), -1)
    remap[used] = np.arange(len(used))
    sensors = []
    for i in range(12):
        zc = _FRONT_Z if i < 6 else _REAR_Z
        sensors.append(
            (i + 1, f"B{i + 1:02d}", "bearing", 0.040 + 0.003 * (i % 6), zc - 0.015 + 0.006 * (i % 6))
        )
    for i in range(20):
        sensors.append((13 + i, f"S{i + 1:02d}", "housing", 0.075 + 0.03 * (i % 2), 0.05 + 0.018 * i))
    parts = tuple(
        SectionPart(name, "steel", r0, r1, z0, z1)
        for name, (r0, r1, z0, z1) in zip(_PART_NAMES, _PARTS, strict=True)
    )
    zones = tuple(ZoneInfo(f"H{i + 1}", text) for i, text in enumerate(_ZONE_TEXT))
    return Section(nodes[used], remap[tris], tuple(sensors), "synthetic-section-v1", parts=parts, zones=zones)


def model_section(*, mesh_size_m: float | None = None) -> Section:
    """The real FE mesh, sensor table and FE steady state from ``model/`` (ImportError if it is missing)."""
    from model import fem, geometry, heat

    spec = geometry.load_spindle()
    fe = fem.build_fe_model(spec, mesh_size_m=mesh_size_m)

    def steady(h: np.ndarray, cond: ConditionSnapshot) -> np.ndarray:
        q_front = float(heat.bearing_heat_w(cond.speed_rpm, cond.torque_nm, spec.bearings.front))
        q_rear = float(heat.bearing_heat_w(cond.speed_rpm, cond.torque_nm, spec.bearings.rear))
        return fem.steady_state(fe, h, ambient_c=cond.ambient_c, q_front_w=q_front, q_rear_w=q_rear)

    sensors = tuple((s.channel, s.name, s.role, s.r_m, s.z_m) for s in spec.sensors)
    parts = tuple(SectionPart(r.name, r.material, r.r0_m, r.r1_m, r.z0_m, r.z1_m) for r in spec.regions)
    zones = tuple(ZoneInfo(z.name, z.description) for z in spec.zones)
    return Section(
        np.asarray(fe.nodes_rz),
        np.asarray(fe.triangles),
        sensors,
        f"fe-{fe.n_nodes}-nodes",
        steady,
        parts=parts,
        zones=zones,
    )


def analytic_field(
    nodes_rz: np.ndarray, h: np.ndarray, cond: ConditionSnapshot, *, rise: float = 1.0
) -> np.ndarray:
    """A smooth stand-in temperature field (°C): two bearing hot spots whose size shrinks as H grows."""
    r, z = nodes_rz[:, 0], nodes_rz[:, 1]
    load = cond.speed_rpm / 1000.0 * (1.0 + 0.05 * cond.torque_nm)
    out = np.full(len(r), cond.ambient_c, dtype=float)
    for zc, hz in ((_FRONT_Z, h[4] + h[5]), (_REAR_Z, h[1] + h[2] + h[3])):
        amp = rise * 4.0 * load * 100.0 / max(float(hz), 1.0)
        out += amp * np.exp(-(((r - _BEARING_R) / 0.05) ** 2) - ((z - zc) / 0.12) ** 2)
    return out


class InMemoryService:
    """A thread-safe, explicitly driven ChtcService (see the module docstring)."""

    def __init__(
        self,
        section: Section | None = None,
        *,
        clock: Clock = utc_now,
        stale_after_s: float = 60.0,
        rng: np.random.Generator | None = None,
        history_capacity: int = 2160,
    ) -> None:
        self._lock = threading.Lock()
        self._compensation: CompensationSnapshot | None = None
        self._section = section if section is not None else synthetic_section()
        self._history = SensorHistoryBuffer(history_capacity, [s[:3] for s in self._section.sensors])
        self._clock = clock
        self._stale_after_s = stale_after_s
        self._rng = rng if rng is not None else np.random.default_rng(0)
        self._started = clock()
        self._condition: ConditionSnapshot | None = None
        self._conditions: deque[ConditionSnapshot] = deque(maxlen=100)
        self._sample: tuple[datetime, np.ndarray, tuple[str, ...]] | None = None
        self._last_good: datetime | None = None  # newest sample with >= MIN_GOOD_CHANNELS ok channels
        self._records: dict[int, IdentificationRecord] = {}
        self._jobs: dict[str, IdentificationJob] = {}
        self._job_ids = itertools.count(1)
        self._devices: dict[str, DeviceHealth] = {}
        self._model_loaded = True
        self._counts = {"modbus": {"ok": 0}, "can": {"ok": 0}, "ident": {"ok": 0, "failed": 0}}
        self._poll_latency = Histogram(LATENCY_BUCKETS_S)
        self._ident_duration = Histogram(DURATION_BUCKETS_S)
        self._snapshot_cache: tuple[tuple[object, ...], ChtcSnapshot] | None = None
        self._field_cache: dict[tuple[int, str], FieldSnapshot] = {}
        self._pred_cache: dict[int, np.ndarray] = {}

    # --- driving the fake -------------------------------------------------------------------------------
    @property
    def section(self) -> Section:
        return self._section

    def set_condition(
        self,
        speed_rpm: float,
        torque_nm: float,
        ambient_c: float,
        *,
        state: str = "stable",
        since: datetime | None = None,
    ) -> None:
        """Start a new condition (a new id) or, with the same values, just update its state."""
        with self._lock:
            now = since or self._clock()
            cur = self._condition
            same = cur is not None and (cur.speed_rpm, cur.torque_nm, cur.ambient_c) == (
                speed_rpm,
                torque_nm,
                ambient_c,
            )
            if same and cur is not None:
                self._condition = replace(cur, state=ConditionState(state))
                self._conditions[0] = self._condition
                return
            new_id = 1 if cur is None else cur.id + 1
            self._condition = ConditionSnapshot(
                new_id, speed_rpm, torque_nm, ambient_c, now, ConditionState(state)
            )
            self._conditions.appendleft(self._condition)

    def add_sample(
        self,
        temps_c: np.ndarray,
        *,
        t: datetime | None = None,
        quality: Sequence[str] | None = None,
        poll_latency_s: float = 0.004,
    ) -> None:
        """Record the newest 32-channel sample (°C), and it with the current prediction in the history."""
        pred = self.predicted_at_sensors()
        with self._lock:
            q = tuple(quality) if quality is not None else ("ok",) * len(temps_c)
            self._sample = (t or self._clock(), np.asarray(temps_c, dtype=float), q)
            if sum(v == "ok" for v in q) >= MIN_GOOD_CHANNELS:
                self._last_good = self._sample[0]
            ok = np.array([x == "ok" for x in q]) & np.isfinite(self._sample[1])
            self._history.append(self._sample[0], np.where(ok, self._sample[1], np.nan), pred)
            self._counts["modbus"]["ok"] += 1
            self._counts["can"]["ok"] += 100
            self._poll_latency.observe(poll_latency_s)

    def add_identification(
        self,
        h: Sequence[float],
        *,
        rel_ci: float = 0.1,
        identified: Sequence[bool] | None = None,
        rmse_c: float = 0.3,
        method: str = "hybrid",
        reason: str = "condition-change",
        outcome: str = "ok",
        wall_s: float = 0.5,
        finished_at: datetime | None = None,
    ) -> IdentificationRecord:
        """Store a finished identification at the current condition and make it the current H."""
        with self._lock:
            if self._condition is None:
                raise NoDataYetError("set_condition() before add_identification()")
            now = finished_at or self._clock()
            hh = np.asarray(h, dtype=float)
            f = rmse_c**2
            data = IdentificationData(
                id=len(self._records) + 1,
                condition_id=self._condition.id,
                started_at=now - timedelta(seconds=wall_s),
                finished_at=now,
                window_start=now - timedelta(minutes=60),
                window_end=now,
                reason=reason,
                outcome=outcome,
                message="converged" if outcome == "ok" else outcome,
                method=method,
                model_version=self._section.model_version,
                h=[float(x) for x in hh],
                ci95_lo=[float(x) for x in hh / (1 + rel_ci)],  # symmetric in log H, as the real one
                ci95_hi=[float(x) for x in hh * (1 + rel_ci)],
                identified=[bool(x) for x in (identified if identified is not None else [True] * 7)],
                f=f,
                fit=1.0 / (1.0 + f),
                rmse_c=rmse_c,
                nfev=120,
                duration_s=wall_s,
                n_sensors_used=32,
            )
            rec = data_to_record(data, self._condition)
            self._records[rec.id] = rec
            self._counts["ident"][outcome] = self._counts["ident"].get(outcome, 0) + 1
            self._ident_duration.observe(wall_s)
            return rec

    def finish_job(self, job_id: str, *, h: Sequence[float], rmse_c: float = 0.3) -> IdentificationRecord:
        """Complete a requested job with the given H (as the worker would)."""
        job = self.job(job_id)
        rec = self.add_identification(h, rmse_c=rmse_c, reason=job.reason)
        with self._lock:
            self._jobs[job_id] = replace(
                job, state=JobState.DONE, finished_at=self._clock(), identification_id=rec.id
            )
        return rec

    def set_device(
        self,
        name: str,
        status: str,
        *,
        last_ok_at: datetime | None = None,
        counters: dict[str, int] | None = None,
        message: str = "",
    ) -> None:
        with self._lock:
            self._devices[name] = DeviceHealth(
                name, DeviceStatus(status), last_ok_at, None, dict(counters or {}), message
            )

    def set_model_loaded(self, loaded: bool) -> None:
        with self._lock:
            self._model_loaded = loaded

    def predicted_at_sensors(self) -> np.ndarray:
        """The stand-in model's prediction (°C) at the 32 sensors for the current H (NaN before any)."""
        snap = self.chtc()
        if snap is None:
            return np.full(len(self._section.sensors), np.nan)
        return self._sensor_prediction(snap)

    # --- ChtcService --------------------------------------------------------------------------------------
    def _latest_ok(self) -> IdentificationRecord | None:
        ok = [r for r in self._records.values() if r.outcome == "ok"]
        return ok[-1] if ok else None

    def _problems(self, now: datetime) -> tuple[str, ...]:
        """Like the running service: the age of the newest good data (enough ok channels) counts."""
        if self._sample is None:
            return ("no_sample: no sample acquired yet",)
        if self._last_good is None:
            return (f"daq_no_good_data: no sample with >= {MIN_GOOD_CHANNELS} usable channels yet",)
        age = (now - self._last_good).total_seconds()
        if age > self._stale_after_s:
            return (
                f"daq_no_good_data: newest sample with >= {MIN_GOOD_CHANNELS} usable channels is "
                f"{age:.0f} s old (limit {self._stale_after_s:.0f} s)",
            )
        return ()

    def _status(self, rec: IdentificationRecord, now: datetime) -> ChtcStatus:
        if self._sample is None:
            return ChtcStatus.NO_DATA
        if self._problems(now):
            return ChtcStatus.STALE
        pending = any(j.state in (JobState.QUEUED, JobState.RUNNING) for j in self._jobs.values())
        cond = self._condition
        if pending or (cond is not None and (cond.id != rec.condition.id or cond.state != "stable")):
            return ChtcStatus.IDENTIFYING
        return ChtcStatus.FRESH

    def chtc(self) -> ChtcSnapshot | None:
        with self._lock:
            rec = self._latest_ok()
            if rec is None:
                return None
            newest = self._sample[0] if self._sample is not None else None
            status = self._status(rec, self._clock())
            key = (rec.id, status, newest)
            if self._snapshot_cache is not None and self._snapshot_cache[0] == key:
                return self._snapshot_cache[1]
            snap = chtc_snapshot(
                rec,
                status=status,
                newest_sample_at=newest,
                condition=self._condition,
                data_problems=tuple(p.split(":")[0] for p in self._problems(self._clock())),
                restored=False,
                box=None,
            )
            self._snapshot_cache = (key, snap)
            return snap

    def _field(self, snap: ChtcSnapshot, at: FieldAt) -> FieldSnapshot:
        """The field for the snapshot's H and condition, cached per identification. "now" is 85 % of the way
        from ambient to steady: a stand-in for the running service's state estimate."""
        key = (snap.identification_id, at)
        if key not in self._field_cache:
            sec, cond = self._section, snap.condition
            if sec.steady is None:
                steady = analytic_field(sec.nodes_rz, snap.h, cond, rise=1.4)
            else:
                steady = np.asarray(sec.steady(snap.h, cond), dtype=float)
            temps = steady if at == "steady" else cond.ambient_c + 0.85 * (steady - cond.ambient_c)
            self._field_cache[key] = FieldSnapshot(
                snap.identified_at, at, sec.nodes_rz, sec.triangles, temps, snap.identification_id
            )
        return self._field_cache[key]

    def field(self, at: FieldAt) -> FieldSnapshot:
        snap = self.chtc()
        if snap is None:
            raise NoDataYetError("no identification yet: no temperature field")
        return self._field(snap, at)

    def _sensor_prediction(self, snap: ChtcSnapshot) -> np.ndarray:
        if snap.identification_id not in self._pred_cache:
            pts = np.array([(s[3], s[4]) for s in self._section.sensors])
            self._pred_cache[snap.identification_id] = self._field(snap, "now").evaluate(pts)
        return self._pred_cache[snap.identification_id]

    def sensors(self) -> Sequence[SensorReading]:
        if self._sample is None:
            raise NoDataYetError("no sample yet")
        t, temps, quality = self._sample
        pred = self.predicted_at_sensors()
        out = []
        for i, (ch, name, role, r, z) in enumerate(self._section.sensors):
            m = float(temps[i]) if quality[i] == "ok" and np.isfinite(temps[i]) else None
            p = float(pred[i]) if np.isfinite(pred[i]) else None
            res = None if m is None or p is None else m - p
            out.append(SensorReading(ch, name, role, r, z, m, p, res, quality[i], t))
        return out

    baseline: OffsetBaseline | None = None  # what request_baseline answers (tests set it)

    def request_baseline(self) -> OffsetBaseline:
        if self.baseline is None:
            raise NotReadyError("no baseline: no samples at rest")
        return self.baseline

    def condition(self) -> ConditionSnapshot:
        if self._condition is None:
            raise NoDataYetError("no operating condition yet (no CAN frame)")
        return self._condition

    def recent_conditions(self, limit: int) -> Sequence[ConditionSnapshot]:
        with self._lock:
            return list(itertools.islice(self._conditions, limit))

    def list_identifications(
        self, *, since: datetime | None, until: datetime | None, limit: int, offset: int
    ) -> IdentificationPage:
        with self._lock:
            rows = sorted(self._records.values(), key=lambda r: (r.finished_at, r.id), reverse=True)
        rows = [
            r
            for r in rows
            if (since is None or r.finished_at >= since) and (until is None or r.finished_at < until)
        ]
        return IdentificationPage(rows[offset : offset + limit], len(rows), limit, offset)

    def get_identification(self, identification_id: int) -> IdentificationRecord:
        try:
            return self._records[identification_id]
        except KeyError:
            raise NotFoundError(f"identification {identification_id} not found") from None

    def request_identification(self, reason: str) -> IdentificationJob:
        with self._lock:
            if not self._model_loaded:
                raise NotReadyError("model not loaded")
            if self._sample is None:
                raise NotReadyError("no samples to identify from")
            busy = [j for j in self._jobs.values() if j.state in (JobState.QUEUED, JobState.RUNNING)]
            if busy:
                raise BusyError(f"identification job {busy[0].job_id} is already {busy[0].state.value}")
            job = IdentificationJob(f"job-{next(self._job_ids)}", reason, JobState.QUEUED, self._clock())
            self._jobs[job.job_id] = job
            return job

    def job(self, job_id: str) -> IdentificationJob:
        try:
            return self._jobs[job_id]
        except KeyError:
            raise NotFoundError(f"job {job_id!r} not found") from None

    def health(self) -> HealthSnapshot:
        with self._lock:
            now = self._clock()
            devices = [
                replace(d, age_s=None if d.last_ok_at is None else (now - d.last_ok_at).total_seconds())
                for d in self._devices.values()
            ]
            version = self._section.model_version if self._model_loaded else None
            return HealthSnapshot(
                now, devices, self._model_loaded, version, (now - self._started).total_seconds()
            )

    def ready(self) -> Readiness:
        reasons = []
        with self._lock:
            if not self._model_loaded:
                reasons.append("model not loaded")
            reasons.extend(self._problems(self._clock()))
        return Readiness(not reasons, tuple(reasons))

    def metrics(self) -> MetricsSnapshot:
        snap = self.chtc()
        with self._lock:
            n = len(self._section.sensors)
            if self._sample is None:
                ages: list[float | None] = [None] * n
                quality: Sequence[str] = ["stale"] * n
            else:
                age = (self._clock() - self._sample[0]).total_seconds()
                ages = [age if q == "ok" else None for q in self._sample[2]]
                quality = self._sample[2]
            last = self._latest_ok()
            return MetricsSnapshot(
                modbus_poll_latency_s=self._poll_latency.snapshot(),
                modbus_polls_total=dict(self._counts["modbus"]),
                can_frames_total=dict(self._counts["can"]),
                channel_age_s=ages,
                channel_quality=list(quality),
                identifications_total=dict(self._counts["ident"]),
                identification_duration_s=self._ident_duration.snapshot(),
                last_fit=None if last is None else last.fit,
                last_rmse_c=None if last is None else last.rmse_c,
                modbus_events_total={"new_samples": self._counts["modbus"]["ok"]},
                can_events_total={"counter_gaps": 0},
                chtc=snap,
                build_version="test",
                model_version=self._section.model_version,
            )

    def sensor_history(self, since: datetime | None) -> SensorHistory:
        return self._history.since(since)

    def layout(self) -> SpindleLayout:
        sec = self._section
        return SpindleLayout(sec.model_version, sec.parts, sec.zones)

    def compensation(self) -> CompensationSnapshot | None:
        """The snapshot given to ``set_compensation``, else a stand-in (no growth model here): the growth
        proportional to the newest sample's mean rise over the ambient (None before an identification)."""
        with self._lock:
            if self._compensation is not None:
                return self._compensation
            sample, cond = self._sample, self._condition
        snap = self.chtc()
        if snap is None or sample is None or cond is None:
            return None
        t, temps, _ = sample
        rise = float(np.nanmean(temps)) - cond.ambient_c if np.any(np.isfinite(temps)) else 0.0
        return stand_in_compensation(snap, at=t, rise_c=rise, ambient_c=cond.ambient_c, n=len(temps))

    def set_compensation(self, snapshot: CompensationSnapshot | None) -> None:
        with self._lock:
            self._compensation = snapshot


def stand_in_compensation(
    snap: ChtcSnapshot, *, at: datetime, rise_c: float, ambient_c: float, n: int
) -> CompensationSnapshot:
    """A plausible ``/compensation`` value for the fake: 1.2 µm/K axial and 0.7 µm/K radial of the mean rise,
    heading to 1.5 times that with a 30-min time constant, 1σ 0.5 µm (the real one: service/engine)."""
    from service.estimate.growth import (
        GrowthEstimate,
        GrowthForecastEstimate,
        GrowthValue,
        plc_compensation,
    )

    axial, radial, tau = 1.2 * rise_c, 0.7 * rise_c, 1800.0
    horizons = (300.0, 900.0, 1800.0)

    def ahead(now: float, h: float) -> GrowthValue:
        return GrowthValue.of(1.5 * now - 0.5 * now * float(np.exp(-h / tau)), 0.5, 0.3)

    growth = GrowthEstimate(
        at=at,
        t_ref_c=ambient_c,
        axial=GrowthValue.of(axial, 0.4, 0.3),
        radial=GrowthValue.of(radial, 0.3, 0.2),
        forecast=GrowthForecastEstimate(
            steady_axial=GrowthValue.of(1.5 * axial, 0.0, 0.6),
            steady_radial=GrowthValue.of(1.5 * radial, 0.0, 0.4),
            tau_s=tau,
            slowest_tau_s=2.0 * tau,
            horizons_s=horizons,
            axial=tuple(ahead(axial, h) for h in horizons),
            radial=tuple(ahead(radial, h) for h in horizons),
        ),
        sensitivity_axial_um_per_k=(0.05,) * n,
        sensitivity_radial_um_per_k=(0.02,) * n,
        h=tuple(float(x) for x in snap.h),
        ambient_c=ambient_c,
    )
    return CompensationSnapshot(
        growth=growth,
        status=snap.status,
        usable_for_compensation=snap.usable_for_compensation,
        reason=snap.reason,
        newest_sample_at=snap.newest_sample_at,
        identification_id=snap.identification_id,
        plc=plc_compensation(axial),
        tool_dir=-1,
        channels=tuple(range(1, n + 1)),
    )


PAPER_H_3000 = (88.21, 46.32, 68.49, 46.72, 52.13, 70.23, 16.54)  # SPEC §2, Table 4
PAPER_H_4000 = (79.75, 46.25, 61.89, 45.31, 46.20, 68.23, 11.12)  # SPEC §2, Table 10


def demo_service(*, clock: Clock = utc_now, section: Section | None = None, seed: int = 0) -> InMemoryService:
    """A populated fake: two conditions (the paper's), two identifications, one sample, healthy devices."""
    svc = InMemoryService(section, clock=clock, rng=np.random.default_rng(seed))
    now = clock()
    svc.set_condition(3000.0, 12.0, 23.2, since=now - timedelta(minutes=95))
    svc.add_identification(
        PAPER_H_3000, identified=[False] + [True] * 6, rmse_c=0.55, finished_at=now - timedelta(minutes=35)
    )
    svc.set_condition(4000.0, 14.0, 21.8, since=now - timedelta(minutes=30))
    svc.add_identification(
        PAPER_H_4000, identified=[False, True, True, False, True, True, True], rmse_c=0.48, wall_s=0.7
    )
    push_noisy_sample(svc, rng=np.random.default_rng(seed))
    svc.set_device("modbus", "ok", last_ok_at=now, counters={"polls": 360, "timeouts": 0})
    svc.set_device("can", "ok", last_ok_at=now, counters={"frames": 36000, "counter_gaps": 2})
    svc.set_device("db", "ok", last_ok_at=now, counters={"rows": 361, "errors": 0})
    return svc


def push_noisy_sample(svc: InMemoryService, *, rng: np.random.Generator, noise_c: float = 0.3) -> None:
    """Add a sample: the stand-in prediction plus Gaussian noise (or ambient + noise before any H)."""
    pred = svc.predicted_at_sensors()
    base = np.where(np.isfinite(pred), pred, svc.condition().ambient_c)
    svc.add_sample(base + rng.normal(0.0, noise_c, len(base)))
