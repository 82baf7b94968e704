"""The core's speed-map track (modes ``speed_map`` and ``combined``, docs/design/hmap.md): the map's own
trigger, the live state's H from the map at each sample's speed, the map fits' launch, outcome and manual
requests. ``MapTrack`` keeps its bookkeeping in a ``service.core.mapbook.MapBook``; ``NoMaps`` stands in
for it in per-condition mode. Pure: no I/O, no clock; the serving strategy (``service.core.serving``)
builds one.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Protocol

import numpy as np

from model.identify_prior import HPrior
from service.core.events import JobOutcomeReceived, Launch, ManualAccepted, RejectKind
from service.core.jobbook import Job, MapValues, job_key
from service.core.jobs import converging_reason, job_request, job_window
from service.core.mapbook import MapBook
from service.core.parts import CoreParts, Out, utc
from service.core.view import NewestSample
from service.estimate.live import LiveStateError
from service.identify import scheduler as sched
from service.identify.detector import OperatingPoint
from service.identify.mapjob import MapJob
from service.identify.prior import job_prior
from service.identify.speedmap import MapConfig, SpeedMap, beyond_box
from service.identify.window import InsufficientWindowError
from service.identify.worker import JobStatus

__all__ = ["MapSide", "MapTrack", "NoMaps"]


class MapSide(Protocol):
    """What the core asks of the map track (``config`` and ``speed_map`` None: no map in this mode)."""

    config: MapConfig | None
    speed_map: SpeedMap | None  # the latest map fit (a restored one is stale until re-fitted)

    def owns(self, job_id: int) -> bool:
        """Whether ``job_id`` is the running map fit."""
        ...

    def condition_started(self, t: float) -> None: ...

    def sample(self, s: NewestSample, ts: float, out: Out) -> None:
        """After the detector saw the sample."""
        ...

    def outcome(self, job: Job, ev: JobOutcomeReceived, ts: float, out: Out) -> None: ...


class NoMaps:
    """No speed map (per-condition mode)."""

    config: MapConfig | None = None
    speed_map: SpeedMap | None = None

    def owns(self, job_id: int) -> bool:
        return False

    def condition_started(self, t: float) -> None:
        return None

    def sample(self, s: NewestSample, ts: float, out: Out) -> None:
        return None

    def outcome(self, job: Job, ev: JobOutcomeReceived, ts: float, out: Out) -> None:
        raise AssertionError(f"no map fit runs, yet {job.key} came back as one")  # owns() is never true


def into_box(
    h: np.ndarray, lo: np.ndarray, hi: np.ndarray, box: tuple[float, float]
) -> tuple[np.ndarray, np.ndarray]:
    """The map's H (7,) with its 95 % band ``lo``..``hi`` as the live state may take it: clipped into the
    reduced model's H box (it holds there only), and which of them are guesses (7,): those whose whole band
    lies outside the box, where the map extrapolated (its level bounds are 0.5–500 W/(m²·K)) and no
    per-condition fit could follow; their considered error is then the guessed one (``CoreParts.h_rel_for``).
    Seen after an airflow change mid-shift: the map put H1 at 500 and H5 at 1 (docs/design/robustness.md)."""
    arr = np.asarray(h, dtype=np.float64)
    return np.clip(arr, float(box[0]), float(box[1])), beyond_box(lo, hi, box)


class MapTrack:
    """See the module docstring."""

    def __init__(self, parts: CoreParts, restored: SpeedMap | None) -> None:
        self.p = parts
        self.config: MapConfig | None = parts.config.speed_map
        self.speed_map: SpeedMap | None = restored
        self.book = MapBook(parts.config, parts.model, restored)

    def owns(self, job_id: int) -> bool:
        return self.book.running == job_id

    def h_prior(self, speed_rpm: float, ambient_c: float) -> HPrior:
        """The prior of a per-condition fit at ``speed_rpm`` [rpm] and ``ambient_c`` [°C] (combined mode): the
        cold physics prior plus the newest map's data information there (``service.identify.prior``)."""
        model = self.p.model
        return job_prior(
            model.spec,
            model.ref.h_box,
            speed_rpm,
            ambient_c,
            speed_map=self.speed_map,
            map_cold=self.book.cold,
            weight=self.book.cfg.prior_weight,
        )

    def condition_started(self, t: float) -> None:
        """A confirmed change triggers a map fit (debounced)."""
        self.book.changed_at = t

    def sample(self, s: NewestSample, ts: float, out: Out) -> None:
        """Serve (combined mode: a change pending since this sample serves the map); count the sample's speed,
        give the live state H from the map at its speed, fit when due."""
        p = self.p
        p.follow_condition()
        p.serve(p.serving.follow(p.condition))
        book = self.book
        book.tally.add(ts, s.speed_rpm, p.config.rules.dt_s)
        self._live_h(s)
        reason = book.due(ts)
        if reason is not None:
            self._launch(ts, reason, out)

    def _live_h(self, s: NewestSample) -> None:
        """The live state's H: the map's (the cold prior's before the first fit) at the sample's speed and
        ambient, with the band as its considered error (recomputed when the speed bin, the map or what serves
        changes); not while a per-condition H serves (combined mode, at a held condition)."""
        book, serving = self.book, self.p.serving
        if not serving.map_serves:
            return
        if not (np.isfinite(s.speed_rpm) and np.isfinite(s.ambient_c)):
            return
        mean, cov, which = book.live_theta(s.t.timestamp(), self.speed_map)
        key = (round(abs(s.speed_rpm) / book.cfg.bin_rpm), round(s.ambient_c), which, serving.generation)
        if key == book.live_key:
            return
        book.live_key = key
        h, lo, hi = book.family.h_ci95_at(mean, cov, [abs(s.speed_rpm)], s.ambient_c)
        inside, guessed = into_box(h[0], lo[0], hi[0], self.p.model.ref.h_box)
        self.p.live.set_h(inside, h_rel=self.p.h_rel_for(h[0], hi[0], guessed))

    def _launch(self, ts: float, reason: str, out: Out) -> str | None:
        """Launch a map fit over the rolling window ending now; None, or why not (stored when it is a job
        that could not run)."""
        p, book = self.p, self.book
        cond = p.condition
        ready = p.live.ready_at()
        if ready is None:
            return converging_reason(p.live)
        if cond is None:
            return "no operating condition yet"
        cfg, dt_s = book.cfg, p.config.rules.dt_s
        t_from = max(ts - cfg.window_s, ready)
        if ts - t_from < cfg.min_window_s - 0.5 * dt_s:
            return (
                f"{ts - t_from:.0f} s of data since the live state converged (need {cfg.min_window_s:.0f} s)"
            )
        jid = p.scheduler.reserve_job_id()
        point = OperatingPoint(speed_rpm=cond.speed_rpm, torque_nm=cond.torque_nm, ambient_c=cond.ambient_c)
        prior, source = book.prior_for(t_from, ts)
        start = sched.StartJob(
            job_id=jid,
            condition_id=cond.id,
            point=point,
            t_from=t_from,
            t_to=ts,
            warm_start=None,
            warm_source=source,
            trigger="map",
        )
        now = utc(ts)
        job = p.jobs.open(start, reason=reason, now=now, event_id=out.event_id)
        rules = replace(p.config.rules, min_window_s=cfg.min_window_s)
        book.changed_at = None
        try:
            window = job_window(start, p.live, p.history, replace(p.config, rules=rules))
        except (InsufficientWindowError, LiveStateError) as err:
            msg = err.reason if isinstance(err, InsufficientWindowError) else str(err)
            p.store_outcome(job, outcome="insufficient-data", message=msg, finished_at=now, out=out)
            book.retry_after = ts + cfg.debounce_s + dt_s
            return msg
        request = job_request(start, window, config=p.config, offsets=p.offsets())
        prior, start_cov = book.intersect(prior, np.array(window.start.cov))
        request = replace(
            request,
            speed_map=MapJob(
                family=cfg.family,
                prior_mean=prior.mean,
                prior_cov=prior.cov,
                start_mean=None if self.speed_map is None else np.array(self.speed_map.mean),
            ),
            start_cov=start_cov,
            carry_start_error=False,
            start_modes=p.config.start_modes,
        )
        snap, arrays = window.start, window.arrays
        job = p.jobs.launched(job, window_from=utc(snap.t), window_to=utc(float(arrays.times_s[-1])))
        book.launched(jid, t_end=float(arrays.times_s[-1]), mask_used=int(arrays.mask.sum()))
        out.instructions.append(Launch(event_id=out.event_id, job_key=job.key, request=request))
        out.log(
            f"map identification {job.key} ({reason}): window {arrays.n_steps * arrays.dt_s / 60:.0f} min, "
            f"{int(arrays.mask.sum())} sensors, prior from {source}"
        )
        return None

    def outcome(self, job: Job, ev: JobOutcomeReceived, ts: float, out: Out) -> None:
        """A map fit came back: keep its posterior (the map served from now on) and store it."""
        p, book = self.p, self.book
        outcome = ev.outcome
        t_end, used, visited = book.finished()
        fit = outcome.map_fit
        if outcome.status is not JobStatus.OK or fit is None:
            kind = "insufficient-data" if outcome.status is JobStatus.INSUFFICIENT_DATA else "failed"
            if outcome.status is JobStatus.CANCELLED:
                kind = "cancelled"
            p.store_outcome(job, outcome=kind, message=outcome.message, finished_at=ev.finished_at, out=out)
            return
        m = SpeedMap(
            family=book.cfg.family,
            mean=fit.posterior.mean,
            cov=fit.posterior.cov,
            visited_rpm=visited[0],
            visited_s=visited[1],
            fitted_at=utc(t_end),
            rmse_c=float(fit.rmse_c),
        )
        cond = p.condition_of(job)
        newest = p.samples.newest
        amb = newest.ambient_c if newest is not None and np.isfinite(newest.ambient_c) else cond.ambient_c
        h, lo, hi = m.h_at([job.start.point.speed_rpm], amb)
        half = 0.5 * np.log(hi[0] / lo[0])
        values = MapValues(
            h=tuple(float(x) for x in h[0]),
            ci95_lo=tuple(float(x) for x in lo[0]),
            ci95_hi=tuple(float(x) for x in hi[0]),
            identified=tuple(bool(x) for x in half <= p.config.ci_threshold),
            rmse_c=float(fit.rmse_c),
            nfev=int(fit.nfev),
            wall_s=float(outcome.wall_s),
            n_sensors_used=used,
            message=outcome.message,
            speed_map=m.to_json(),
        )
        data, rec = p.jobs.mapped(
            job, values=values, finished_at=ev.finished_at, event_id=out.event_id, condition=cond
        )
        out.store(data)
        self.speed_map = replace(m, identification_id=data.id)
        book.keep(t_end, fit.posterior)
        p.serve(p.serving.mapped(rec, p.condition))
        out.log(
            f"map identification {job.key} ok: {fit.nfev} model runs, RMSE {fit.rmse_c:.3f} °C, "
            f"{outcome.wall_s:.2f} s; visited {len(visited[0])} speed bins"
        )

    def manual(self, reason: str, newest: NewestSample, out: Out) -> None:
        """A map fit requested through the API (speed-map and combined mode)."""
        book = self.book
        if book.running is not None:
            out.reject(RejectKind.BUSY, f"map identification {job_key(book.running)} is already running")
            return
        ts = newest.t.timestamp()
        why = self._launch(ts, (reason or "manual")[:32], out)
        launched = next((i for i in out.instructions if isinstance(i, Launch)), None)
        if launched is None:
            out.reject(RejectKind.NOT_READY, why or "no map identification possible now")
            return
        out.instructions.append(ManualAccepted(out.event_id, self.p.jobs.jobs_view[launched.job_key]))
