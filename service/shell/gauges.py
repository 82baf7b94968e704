"""The running service's device health and metrics (``/healthz``, ``/metrics``): read from the parts the shell
owns (the acquisition's sources, the database writer, the identification worker, the core's runner, the
event loop's lag) and a published view. The per-device readings are ``service.shell.health``'s pure
functions; this module gathers them."""

from __future__ import annotations

import functools
from collections.abc import Callable, Mapping
from datetime import datetime
from typing import TYPE_CHECKING

from service.contracts.health import DeviceHealth, DeviceStatus
from service.contracts.metrics import (
    CoreMetrics,
    FilterMetrics,
    HistogramData,
    MetricsSnapshot,
    OutletMetrics,
)
from service.contracts.snapshots import ChtcSnapshot
from service.serve.histogram import LATENCY_BUCKETS_S, Histogram
from service.serve.view import CoreView
from service.shell.corethread import CoreRunner
from service.shell.health import (
    HealthSource,
    StatusSource,
    core_health,
    db_health,
    filter_health,
    frame_events,
    frame_outcomes,
    loop_health,
    poll_events,
    poll_outcomes,
    source_health,
)
from service.shell.looplag import LoopLagMonitor

if TYPE_CHECKING:
    from service.shell.ports import Worker

__all__ = ["Gauges"]

Clock = Callable[[], datetime]


class Gauges:
    """The device health and the metrics of one running service (see the module docstring)."""

    def __init__(
        self,
        *,
        sources: Mapping[str, HealthSource],
        writer: StatusSource | None,
        worker: Worker | None,
        runner: CoreRunner,
        loop_lag: LoopLagMonitor | None,
        clock: Clock,
    ) -> None:
        self.sources = dict(sources)
        self.writer = writer
        self.worker = worker
        self.runner = runner
        self.loop_lag = loop_lag
        self.clock = clock
        self.poll_latency = Histogram(LATENCY_BUCKETS_S)
        modbus = self.sources.get("modbus")
        if modbus is not None and hasattr(modbus, "on_read_s"):
            modbus.on_read_s = self.poll_latency.observe  # the driver's own poll timing (drivers.base)

    def devices(self, view: CoreView, now: datetime | None = None) -> list[DeviceHealth]:
        """The device health at ``now`` (default: the clock's) with ``view``."""
        now = self.clock() if now is None else now
        out = [source_health(name, src, now) for name, src in self.sources.items()]
        out.append(db_health(self.writer, now))
        out.append(self.worker_health(view))
        out.append(filter_health(view, now))
        if self.runner.load().threaded:
            out.append(core_health(self.runner.load(), view, now))
        if self.loop_lag is not None:
            out.append(loop_health(self.loop_lag.lag()))
        return out

    def worker_health(self, view: CoreView) -> DeviceHealth:
        if self.worker is None:
            return DeviceHealth(
                name="worker",
                status=DeviceStatus.DISABLED,
                last_ok_at=None,
                age_s=None,
                counters={},
                message="no identification worker",
            )
        status = DeviceStatus.OK if self.worker.model_version is not None else DeviceStatus.DOWN
        counters = {"restarts": self.worker.restarts, **view.counts}
        running = self.worker.running_job
        msg = f"running job-{running}" if running is not None else "idle"
        return DeviceHealth(
            name="worker", status=status, last_ok_at=None, age_s=None, counters=counters, message=msg
        )

    def metrics(
        self,
        v: CoreView,
        *,
        chtc: ChtcSnapshot | None,
        model_version: str | None,
        growth_terms: tuple[int, float],
        outlets: dict[str, OutletMetrics],
    ) -> MetricsSnapshot:
        """``/metrics`` of ``v`` now: ``chtc`` the served H, ``growth_terms`` the condition terms computed
        and their CPU [s], ``outlets`` each counted outlet's counters."""
        now = self.clock()
        modbus = self.sources.get("modbus")
        can = self.sources.get("can")
        ages = v.channel_ages(now)
        quality = list(v.newest.quality) if v.newest is not None else ["no_data"] * len(ages)
        last = v.current
        st = self.writer.status() if self.writer is not None else None
        reconnects = {n: int(s.metrics.reconnects) for n, s in self.sources.items()}
        if self.worker is not None:
            reconnects["worker"] = self.worker.restarts
        return MetricsSnapshot(
            modbus_poll_latency_s=self.poll_latency.snapshot(),
            modbus_polls_total=poll_outcomes(modbus),
            can_frames_total=frame_outcomes(can),
            modbus_events_total=poll_events(modbus),
            can_events_total=frame_events(can),
            chtc=chtc,
            build_version=_build_version(),
            model_version=model_version,
            channel_age_s=ages,
            channel_quality=quality,
            identifications_total=dict(v.counts),
            identification_duration_s=v.durations,
            last_fit=None if last is None else last.fit,
            last_rmse_c=None if last is None else last.rmse_c,
            db_pending_rows=0 if st is None else int(st.pending),
            db_errors_total=0 if st is None else int(st.errors),
            db_write_s=_write_latency(self.writer),
            reconnects_total=reconnects,
            filter=_filter_metrics(v),
            loop_lag_s=None if self.loop_lag is None else self.loop_lag.histogram.snapshot(),
            loop_lag_recent_max_s=None if self.loop_lag is None else self.loop_lag.lag().recent_max_s,
            core=self._core_metrics(v, now),
            growth_terms_computed=growth_terms[0],
            growth_terms_cpu_s=growth_terms[1],
            outlets=outlets,
        )

    def _core_metrics(self, v: CoreView, now: datetime) -> CoreMetrics | None:
        wait = self.runner.wait_s()
        if wait is None:
            return None
        load = self.runner.load()
        return CoreMetrics(
            wait_s=wait.snapshot(),
            queued=load.queued,
            lag_s=v.core_lag_s(now),
            dropped=load.dropped,
            handled=load.handled,
        )


def _write_latency(writer: object) -> HistogramData | None:
    """The database writer's batch latencies, if it keeps them (``persistence.GateSink`` does)."""
    hist = getattr(writer, "write_latency", None)
    return None if hist is None else hist.snapshot()


def _filter_metrics(v: CoreView) -> FilterMetrics | None:
    live = v.live
    if live is None:
        return None
    return FilterMetrics(
        nis=live.nis,
        dof=live.nis_dof,
        window_ratio=live.nis_sum / live.nis_sum_dof if live.nis_sum_dof else None,
        verdict=live.verdict,
        converged=live.converged,
        inconsistent=live.inconsistent(live.t),
    )


@functools.cache
def _build_version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("spindle-chtc")
    except PackageNotFoundError:
        return "unknown"
