"""The read side of the running service: :class:`ViewReader` answers from one published ``CoreView``.

The shell (``service.shell.service.SoftSensorService``) publishes an immutable
:class:`~service.serve.view.CoreView` after each event; every outlet (REST, OPC UA, MQTT) reads the same
values with the same statuses through a ``ViewReader`` built from that view and one long-lived
:class:`ReadContext` (the clock, the model, the growth server, the device health and the snapshot caches
shared by all readers). A reader holds no lock: the view is
frozen, the caches are swapped by one reference. Ages and data problems are taken at the reader's ``clock()``
when a method is called, so a reader kept after its view was replaced still ages correctly (an outlet that
evaluates the same reader again later sees its values go stale).

The writes (``request_identification``, baselines, references, probes) and the database history stay with the
shell: they hand events to the core or read the database, not a view.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from datetime import UTC, datetime
from typing import TYPE_CHECKING, Protocol

import numpy as np

from model.defaults import BOUND_REL_TOL
from model.hmap import LEVEL_BOUNDS
from service.contracts.errors import NoDataYetError, NotFoundError
from service.contracts.health import DeviceHealth, HealthSnapshot, Readiness
from service.contracts.mechanics import MechanicsCalibration
from service.contracts.mode import IdentificationMode
from service.contracts.probe import ProbeMeasurement
from service.contracts.reference import CompensationReference
from service.contracts.snapshots import (
    ZONE_NAMES,
    ChtcMapSnapshot,
    ChtcSnapshot,
    CompensationSnapshot,
    ConditionSnapshot,
    FieldAt,
    FieldSnapshot,
    IdentificationJob,
    SectionPart,
    SectionSnapshot,
    SensorReading,
    SpindleLayout,
    ZoneInfo,
)
from service.contracts.verdict import DataProblem, Verdict
from service.estimate.live import steady_field
from service.identify.prior import ServedMapPrior
from service.serve.policy import chtc_verdict, map_verdict
from service.serve.view import CoreView
from service.serve.views import at_bound, chtc_map_snapshot, chtc_snapshot, map_record, served_record

if TYPE_CHECKING:
    from service.modelload import LoadedModel

__all__ = ["MAP_H_BOX", "GrowthReads", "NewestViewReads", "ReadContext", "ViewReader"]

Clock = Callable[[], datetime]
# the speed map's bounds of H, W/(m²·K) (its family's ln-H bounds)
MAP_H_BOX = (float(np.exp(LEVEL_BOUNDS[0])), float(np.exp(LEVEL_BOUNDS[1])))


class GrowthReads(Protocol):
    """What a reader needs of the growth server (``service.serve.compensation.GrowthServer``)."""

    @property
    def reference(self) -> CompensationReference | None: ...

    @property
    def mechanics(self) -> MechanicsCalibration | None: ...

    def probes(self) -> list[ProbeMeasurement]: ...

    def snapshot(self, view: CoreView, now: datetime) -> CompensationSnapshot | None: ...

    def section_snapshot(self, view: CoreView, now: datetime) -> SectionSnapshot | None: ...


class ReadContext:
    """What every reader shares: injected once by the shell, with the caches of the costly snapshots.

    ``devices(view, now)`` lists the device health (the shell owns the sources, writer and worker);
    ``model_loaded()`` says whether the identification worker has loaded its model.
    """

    def __init__(
        self,
        model: LoadedModel,
        *,
        clock: Clock,
        mode: IdentificationMode,
        growth: GrowthReads,
        devices: Callable[[CoreView, datetime], Sequence[DeviceHealth]],
        model_loaded: Callable[[], bool],
        started_mono: float | None = None,
    ) -> None:
        self.model = model
        self.clock = clock
        self.mode = mode
        self.growth = growth
        self.devices = devices
        self.model_loaded = model_loaded
        self.started_mono = time.monotonic() if started_mono is None else started_mono
        # /chtc from the map: its information on the cold physics prior (finite, honest bands)
        self.map_prior = ServedMapPrior(model.spec, model.ref.h_box)
        self.snap_cache: tuple[tuple[object, ...], ChtcSnapshot] | None = None
        self.map_cache: tuple[tuple[object, ...], ChtcMapSnapshot] | None = None
        self.steady_cache: tuple[tuple[object, ...], FieldSnapshot] | None = None


class ViewReader:
    """The served values of one view (see the module docstring). Cheap to build: one per read is fine."""

    def __init__(self, view: CoreView, ctx: ReadContext) -> None:
        self.view = view
        self.ctx = ctx

    def now(self) -> datetime:
        return self.ctx.clock()

    # --- H ----------------------------------------------------------------------------------------------
    def chtc(self) -> ChtcSnapshot | None:
        v, ctx = self.view, self.ctx
        rec = v.current
        if rec is None:
            return None
        now = ctx.clock()
        newest = v.newest.t if v.newest is not None else None
        problems = problem_codes(v, now)
        box: tuple[float, float] | None = ctx.model.ref.h_box
        cond = v.condition
        live = v.live
        since = None if live is None or live.converged else _utc(live.started_at)
        # the serving strategy's verdict (map_serves): per-condition mode, and combined mode at a held
        # condition, serve an identification; the map's H elsewhere
        fresh = self._map_verdict(problems, since) if v.map_serves else None
        if fresh is not None and v.speed_map is not None and cond is not None and v.newest is not None:
            # speed-map mode: H from the map at the newest sample's speed and ambient, at once
            s = v.newest
            speed, ambient = _finite_or(s.speed_rpm, cond.speed_rpm), _finite_or(s.ambient_c, cond.ambient_c)
            level_sd = 0.0 if v.map_config is None else v.map_config.prior_level_sd
            rec = map_record(
                rec,
                v.speed_map,
                speed_rpm=speed,
                ambient_c=ambient,
                condition=cond,
                ci_threshold=v.ci_threshold,
                prior=ctx.map_prior.at(v.speed_map, level_sd=level_sd, speed_rpm=speed, ambient_c=ambient),
                model_box=box,
            )
            # the map's search box is its family's bounds (model.hmap.LEVEL_BOUNDS), not the per-condition
            # one: an H there is never fresh (at-bound), as in per-condition mode
            box = MAP_H_BOX
        faults = () if live is None else live.sensor_faults
        key = (
            rec.id,
            newest,
            cond.id if cond else None,
            cond.state if cond else None,
            problems,
            since,
            v.running_job is not None,
            v.current_from_restore,
            None if fresh is None else (id(v.speed_map), fresh),
            faults,
        )
        cached = ctx.snap_cache
        if cached is not None and cached[0] == key:
            return cached[1]
        if box is not None:
            rec = served_record(rec, form_sd=v.h_form_sd, ci_threshold=v.ci_threshold, box=box)
        bound = at_bound(rec, box, BOUND_REL_TOL)
        verdict = chtc_verdict(
            has_sample=newest is not None,
            problems=problems,
            live=live,
            now=now,
            condition=cond,
            record_condition_id=rec.condition.id,
            map_verdict=fresh,
            running=v.running_job is not None,
            bound=[bool(b) for b in bound],
            identified=[bool(b) for b in rec.identified],
            prior_dominated=[bool(b) for b in rec.prior_dominated],
            h=[float(x) for x in rec.h],
            restored=v.current_from_restore,
            zones=ZONE_NAMES,
        )
        snap = chtc_snapshot(
            rec, newest_sample_at=newest, verdict=verdict, bound=bound, box=box, sensor_faults=faults
        )
        ctx.snap_cache = (key, snap)
        return snap

    def _map_verdict(self, problems: tuple[DataProblem, ...], since: datetime | None) -> Verdict | None:
        """With a map (speed-map or combined mode): how current it is at the newest sample's speed (else
        None). A sample without a speed value (one missing CAN value) is still a sample: the speed is the
        condition's then, as ``chtc()`` serves the map at (issue 26: it turned /chtc to ``no-data``)."""
        v = self.view
        cfg, m = v.map_config, v.speed_map
        if cfg is None or m is None:
            return None
        s, cond = v.newest, v.condition
        speed: float | None = None
        if s is not None and np.isfinite(s.speed_rpm):
            speed = float(s.speed_rpm)
        elif cond is not None and np.isfinite(cond.speed_rpm):
            speed = float(cond.speed_rpm)
        return map_verdict(
            m,
            newest_t=None if s is None else s.t,
            speed_rpm=speed,
            problems=problems,
            converging_since=since,
            fresh_s=cfg.fresh_s,
            margin_rpm=cfg.margin_rpm,
            min_visit_s=cfg.min_visit_s,
        )

    def identification_mode(self) -> IdentificationMode:
        return self.ctx.mode

    def chtc_map(self) -> ChtcMapSnapshot | None:
        v, ctx = self.view, self.ctx
        cfg, m = v.map_config, v.speed_map
        if cfg is None or m is None:
            return None
        s = v.newest
        newest = None if s is None else s.t
        problems = problem_codes(v, ctx.clock())
        live = v.live
        since = None if live is None or live.converged else _utc(live.started_at)
        fresh = self._map_verdict(problems, since)
        assert fresh is not None
        ambient = 20.0 if s is None or not np.isfinite(s.ambient_c) else round(float(s.ambient_c), 1)
        speed = None if s is None or not np.isfinite(s.speed_rpm) else float(s.speed_rpm)
        key = (id(m), ambient, newest, speed, fresh)
        cached = ctx.map_cache
        if cached is not None and cached[0] == key:
            return cached[1]
        snap = chtc_map_snapshot(
            m,
            ambient_c=ambient,
            verdict=fresh,
            newest_sample_at=newest,
            current_speed_rpm=speed,
            ci_threshold=v.ci_threshold,
            margin_rpm=cfg.margin_rpm,
            form_sd=v.h_form_sd,
            box=MAP_H_BOX,
            model_box=ctx.model.ref.h_box,
        )
        ctx.map_cache = (key, snap)
        return snap

    # --- field, growth, sensors ---------------------------------------------------------------------------
    def field(self, at: FieldAt) -> FieldSnapshot:
        v, ctx = self.view, self.ctx
        rec = v.current
        if rec is None:
            raise NoDataYetError("no identification yet: no temperature field")
        live = v.live
        if live is None:
            raise NoDataYetError("no sample yet: the live temperature field has not started")
        fe = ctx.model.fe
        if at == "now":
            # the filtered estimate and its 1σ (computed once per view, on the first request)
            return FieldSnapshot(
                _utc(live.t), "now", fe.nodes_rz, fe.triangles, live.field_c, rec.id, std_c=live.field_std_c
            )
        key = (rec.id, v.condition.id if v.condition else None)
        cached = ctx.steady_cache
        if cached is not None and cached[0] == key:
            return cached[1]
        steady = steady_field(fe, ctx.model.spec, live)
        out = FieldSnapshot(ctx.clock(), "steady", fe.nodes_rz, fe.triangles, steady, rec.id)
        ctx.steady_cache = (key, out)
        return out

    def compensation(self) -> CompensationSnapshot | None:
        return self.ctx.growth.snapshot(self.view, self.ctx.clock())

    def compensation_section(self) -> SectionSnapshot | None:
        return self.ctx.growth.section_snapshot(self.view, self.ctx.clock())

    def compensation_reference(self) -> CompensationReference | None:
        return self.ctx.growth.reference

    def compensation_mechanics(self) -> MechanicsCalibration | None:
        return self.ctx.growth.mechanics

    def compensation_measurements(self) -> list[ProbeMeasurement]:
        """The probe readings kept (restored and new), newest first."""
        return self.ctx.growth.probes()

    def sensors(self) -> Sequence[SensorReading]:
        v = self.view
        s = v.newest
        if s is None:
            raise NoDataYetError("no sample yet")
        live = v.live
        pred = None if live is None else live.sensors_c
        pred_sd = None if live is None else live.sensors_std_c
        cal, sd = v.calibration, v.offset_sd_c
        applied = cal.applied() if cal is not None else None
        out = []
        for i, spec in enumerate(self.ctx.model.spec.sensors):
            q = s.quality[i] if i < len(s.quality) else "no_data"
            m = float(s.temps_c[i]) if q == "ok" and np.isfinite(s.temps_c[i]) else None
            p = float(pred[i]) if pred is not None else None
            off = float(applied[i]) if applied is not None else None
            res = m - (off or 0.0) - p if m is not None and p is not None else None  # offset-corrected
            out.append(
                SensorReading(
                    *(spec.channel, spec.name, spec.role, spec.r_m, spec.z_m, m, p, res, q, s.t),
                    offset_c=off,
                    offset_sd_c=None if sd is None else float(sd[i]),
                    offset_calibrated_at=None if cal is None else cal.t_to,
                    offset_source=None if cal is None else cal.source,
                    predicted_sd_c=None if pred_sd is None else float(pred_sd[i]),
                )
            )
        return out

    # --- condition, jobs, layout --------------------------------------------------------------------------
    def condition(self) -> ConditionSnapshot:
        cond = self.view.condition
        if cond is None:
            raise NoDataYetError("no operating condition yet")
        return cond

    def recent_conditions(self, limit: int) -> Sequence[ConditionSnapshot]:
        return list(self.view.conditions[: max(0, limit)])

    def job(self, job_id: str) -> IdentificationJob:
        job = self.view.jobs.get(job_id)
        if job is None:
            raise NotFoundError(f"job {job_id!r} not found")
        return job

    def layout(self) -> SpindleLayout:
        spec = self.ctx.model.spec
        parts = tuple(
            SectionPart(name=r.name, material=r.material, r0_m=r.r0_m, r1_m=r.r1_m, z0_m=r.z0_m, z1_m=r.z1_m)
            for r in spec.regions
        )
        zones = tuple(ZoneInfo(z.name, z.description) for z in spec.zones)
        return SpindleLayout(name=spec.name, parts=parts, zones=zones)

    # --- health -------------------------------------------------------------------------------------------
    def devices(self) -> list[DeviceHealth]:
        return list(self.ctx.devices(self.view, self.ctx.clock()))

    def health(self) -> HealthSnapshot:
        ctx = self.ctx
        loaded = ctx.model_loaded()
        return HealthSnapshot(
            t=ctx.clock(),
            devices=self.devices(),
            model_loaded=loaded,
            model_version=ctx.model.version if loaded else None,
            uptime_s=time.monotonic() - ctx.started_mono,
        )

    def ready(self) -> Readiness:
        reasons = []
        if not self.ctx.model_loaded():
            reasons.append("model not loaded")
        reasons.extend(str(p) for p in self.view.data_problems(self.ctx.clock()))
        return Readiness(not reasons, tuple(reasons))


class NewestViewReads:
    """The read side of ``service.serve.interface.ChtcService`` for whatever publishes views (the running
    service's ``SoftSensorService``): each read is answered by ``reader()``, a :class:`ViewReader` of the
    newest published view, the same values every outlet serves."""

    def reader(self) -> ViewReader:
        raise NotImplementedError

    def chtc(self) -> ChtcSnapshot | None:
        return self.reader().chtc()

    def chtc_map(self) -> ChtcMapSnapshot | None:
        return self.reader().chtc_map()

    def identification_mode(self) -> IdentificationMode:
        return self.reader().identification_mode()

    def field(self, at: FieldAt) -> FieldSnapshot:
        return self.reader().field(at)

    def compensation(self) -> CompensationSnapshot | None:
        return self.reader().compensation()

    def compensation_section(self) -> SectionSnapshot | None:
        return self.reader().compensation_section()

    def compensation_reference(self) -> CompensationReference | None:
        return self.reader().compensation_reference()

    def compensation_mechanics(self) -> MechanicsCalibration | None:
        return self.reader().compensation_mechanics()

    def compensation_measurements(self) -> list[ProbeMeasurement]:
        return self.reader().compensation_measurements()

    def sensors(self) -> Sequence[SensorReading]:
        return self.reader().sensors()

    def condition(self) -> ConditionSnapshot:
        return self.reader().condition()

    def recent_conditions(self, limit: int) -> Sequence[ConditionSnapshot]:
        return self.reader().recent_conditions(limit)

    def layout(self) -> SpindleLayout:
        return self.reader().layout()

    def job(self, job_id: str) -> IdentificationJob:
        return self.reader().job(job_id)

    def health(self) -> HealthSnapshot:
        return self.reader().health()

    def ready(self) -> Readiness:
        return self.reader().ready()


def problem_codes(v: CoreView, now: datetime) -> tuple[DataProblem, ...]:
    """The data problems by code only (their ages change every second: the snapshots and their ETags stay put
    while stale; the ages are on /readyz); none before the first sample (``no_data`` then)."""
    if v.newest is None:
        return ()
    return tuple(DataProblem(p.code, "") for p in v.data_problems(now))


def _finite_or(x: float, fallback: float) -> float:
    return float(x) if np.isfinite(x) else float(fallback)


def _utc(ts: float) -> datetime:
    return datetime.fromtimestamp(ts, tz=UTC)
