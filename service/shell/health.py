"""Device health and metric counters from the acquisition sources and the database writer (pure readers).

The shell (``service.shell.service``) calls these for ``/healthz`` and ``/metrics``; the sources are
``drivers.base.Source`` objects (read only here), the writer is the buffered database writer.
"""

from __future__ import annotations

from collections.abc import Callable
from datetime import datetime
from typing import Protocol

from drivers.base import SourceMetrics
from service.contracts.health import DeviceHealth, DeviceStatus
from service.core.view import CoreView
from service.serve.views import age_s
from service.shell.corethread import CoreLoad
from service.shell.looplag import LoopLag
from service.store.writer import WriterStatus

__all__ = [
    "HealthSource",
    "StatusSource",
    "core_health",
    "db_health",
    "filter_health",
    "frame_events",
    "frame_outcomes",
    "loop_health",
    "poll_events",
    "poll_outcomes",
    "source_health",
]


class HealthSource(Protocol):
    """What health and metrics read from an acquisition source (``drivers.base.Source``)."""

    metrics: SourceMetrics
    on_read_s: Callable[[float], None] | None

    @property
    def connected(self) -> bool: ...

    def is_stale(self) -> bool: ...

    def condition(self) -> str: ...


class StatusSource(Protocol):
    """The database writer as health reads it (``DbWriter`` / ``GateSink``)."""

    def status(self) -> WriterStatus: ...


def source_health(name: str, src: HealthSource, now: datetime) -> DeviceHealth:
    m = src.metrics
    last_ok = m.last_ok_t
    if not src.connected:
        status = DeviceStatus.DOWN
    elif src.is_stale() or m.errors:
        status = DeviceStatus.DEGRADED if not src.is_stale() else DeviceStatus.DOWN
    else:
        status = DeviceStatus.OK
    recent_error = m.last_error_t is not None and (now - m.last_error_t).total_seconds() <= 60.0
    if status is DeviceStatus.DEGRADED and not recent_error:
        status = DeviceStatus.OK  # old errors only: healthy again
    condition = src.condition()  # e.g. CAN fault status
    if condition and status is DeviceStatus.OK:
        status = DeviceStatus.DEGRADED
    counters = {
        "polls": m.polls,
        "reads_ok": m.reads_ok,
        "reconnects": m.reconnects,
        **m.errors,
        **m.events,
    }
    # a recovered device's error is history; a CAN warning/fault status is the reason while it lasts
    message = condition or (m.last_error if status is not DeviceStatus.OK else "")
    return DeviceHealth(
        name=name,
        status=status,
        last_ok_at=last_ok,
        age_s=age_s(last_ok, now),
        counters=counters,
        message=message,
    )


def db_health(writer: StatusSource | None, now: datetime) -> DeviceHealth:
    """The database writer's health (DISABLED without a database)."""
    if writer is None:
        return DeviceHealth(
            name="db",
            status=DeviceStatus.DISABLED,
            last_ok_at=None,
            age_s=None,
            counters={},
            message="no database configured",
        )
    st = writer.status()
    status = DeviceStatus.OK if st.connected else DeviceStatus.DOWN
    busy_s = st.busy_s
    hung = busy_s is not None and busy_s > st.stall_s
    if st.connected and (st.pending > 1000 or hung):
        status = DeviceStatus.DEGRADED
    counters = {
        "pending": st.pending,
        "written": st.written,
        "dropped": st.dropped,
        "rejected": st.rejected,
        "errors": st.errors,
    }
    msg = "" if st.connected else f"buffering {st.pending} records: {st.last_error or 'not connected yet'}"
    if hung:
        msg = f"database not answering for {busy_s:.0f} s; buffering {st.pending} records"
    return DeviceHealth(
        name="db",
        status=status,
        last_ok_at=st.last_ok_at,
        age_s=age_s(st.last_ok_at, now),
        counters=counters,
        message=msg,
    )


def poll_outcomes(src: HealthSource | None) -> dict[str, int]:
    """Modbus polls by outcome, one per poll: "ok", each failure by error class ("device_timeout",
    "short_reply", "modbus_exception", ...) and "link_down" (refused while a reconnect was not yet due)."""
    if src is None:
        return {}
    m = src.metrics
    out = {"ok": int(m.reads_ok), "link_down": int(m.events.get("polls_while_down", 0))}
    for name, n in m.errors.items():
        out[_snake(name)] = out.get(_snake(name), 0) + int(n)
    return out


def poll_events(src: HealthSource | None) -> dict[str, int]:
    """Modbus events (not outcomes): "new_samples", "stale_polls", "restarts", ..."""
    if src is None:
        return {}
    return {_snake(k): int(n) for k, n in src.metrics.events.items() if k != "polls_while_down"}


def _frame_error(name: str) -> bool:
    """Whether an error class name (drivers.errors) is a rejected frame (not a counter gap on a good one)."""
    from drivers import errors

    cls = getattr(errors, name, None)
    return (
        isinstance(cls, type)
        and issubclass(cls, errors.FrameError)
        and not issubclass(cls, errors.CounterGapError)
    )


def frame_outcomes(src: HealthSource | None) -> dict[str, int]:
    """CAN frames by outcome, one per frame read: "ok" or the reason it was rejected ("unknown_frame_id",
    "wrong_dlc", "bad_signal", ...)."""
    if src is None:
        return {}
    m = src.metrics
    out = {"ok": int(m.reads_ok)}
    for name, n in m.errors.items():
        if _frame_error(name):
            out[_snake(name)] = out.get(_snake(name), 0) + int(n)
    return out


def frame_events(src: HealthSource | None) -> dict[str, int]:
    """CAN events: the driver's counters ("counter_gaps", "frames_lost", "faults", "warnings", ...) and the
    errors that are no frame ("device_timeout": silence, "device_unavailable": bus down)."""
    from drivers import errors

    if src is None:
        return {}
    m = src.metrics
    out = {_snake(k): int(n) for k, n in m.events.items()}
    for name, n in m.errors.items():
        cls = getattr(errors, name, None)
        if not _frame_error(name) and not (isinstance(cls, type) and issubclass(cls, errors.CounterGapError)):
            out[_snake(name)] = out.get(_snake(name), 0) + int(n)
    return out


def _snake(name: str) -> str:
    out = "".join("_" + c.lower() if c.isupper() else c for c in name).lstrip("_")
    return out.removesuffix("_error") or out


def filter_health(view: CoreView, now: datetime) -> DeviceHealth:
    """The live state's Kalman filter as a ``/healthz`` device ("filter").

    ``ok`` when converged and its innovations are consistent (the NIS window in its χ² band, or filling,
    or below it: cautious); ``degraded`` while converging after a (re)start (reason ``state_converging``)
    or when the NIS has been above its band for ``FilterSettings.inconsistent_after_s`` (reason
    ``filter_inconsistent``: the model misses something, a heat source or a drifting sensor); ``down``
    before the first sample with ambient, speed and torque. Counters: the NIS window's Σ dof; the message
    gives the verdict, Σ NIS against its band and the last sample's NIS/dof."""
    live = view.live
    if live is None:
        return DeviceHealth(
            name="filter",
            status=DeviceStatus.DOWN,
            last_ok_at=None,
            age_s=None,
            message="not started: no sample with inputs",
        )
    t = datetime.fromtimestamp(live.t, tz=now.tzinfo)
    lo, hi = live.nis_band
    figures = (
        f"NIS {live.verdict}: Σ {live.nis_sum:.1f} over {live.nis_sum_dof} dof, band [{lo:.1f}, {hi:.1f}]; "
        f"last sample {live.nis:.1f}/{live.nis_dof}"
    )
    counters = {"nis_window_dof": live.nis_sum_dof, "last_sample_dof": live.nis_dof}
    age = age_s(t, now)
    status, msg = DeviceStatus.OK, figures
    if not live.converged:
        status, msg = DeviceStatus.DEGRADED, f"state_converging: {live.reason}; {figures}"
    elif live.inconsistent(live.t):
        since = live.t - (live.high_since or live.t)
        msg = f"filter_inconsistent: NIS above its band for {since / 60:.0f} min; {figures}"
        status = DeviceStatus.DEGRADED
    return DeviceHealth(name="filter", status=status, last_ok_at=t, age_s=age, counters=counters, message=msg)


def core_health(load: CoreLoad, view: CoreView, now: datetime) -> DeviceHealth:
    """The core thread as a ``/healthz`` device ("core"): ``degraded`` while a sample has waited for it longer
    than ``view.max_core_lag_s`` (reason ``core_behind``: the served values say so too), ``ok`` otherwise.
    Counters: events queued, handled, samples dropped (queue full)."""
    lag = view.core_lag_s(now)
    counters = {"queued": load.queued, "handled": load.handled, "dropped": load.dropped}
    figures = f"{load.queued} queued (capacity {load.capacity}), oldest sample waits {lag:.2f} s"
    behind = lag > view.max_core_lag_s
    return DeviceHealth(
        name="core",
        status=DeviceStatus.DEGRADED if behind else DeviceStatus.OK,
        last_ok_at=None,
        age_s=None,
        counters=counters,
        message=f"core_behind: {figures} (limit {view.max_core_lag_s:g} s)" if behind else figures,
    )


def loop_health(lag: LoopLag) -> DeviceHealth:
    """The event loop as a ``/healthz`` device ("event_loop"): ``degraded`` when its largest lag of the last
    ``lag.window_s`` exceeds ``lag.limit_s`` (``loop_lagging``: requests and acquisition wait that long)."""
    ms, limit_ms = 1e3 * lag.recent_max_s, 1e3 * lag.limit_s
    figures = f"max lag {ms:.1f} ms in the last {lag.window_s:g} s (limit {limit_ms:g} ms)"
    return DeviceHealth(
        name="event_loop",
        status=DeviceStatus.DEGRADED if lag.over_limit else DeviceStatus.OK,
        last_ok_at=None,
        age_s=None,
        counters={"observations": lag.observations},
        message=f"loop_lagging: {figures}" if lag.over_limit else figures,
    )
