"""The numbers the service exposes (``/metrics``, Prometheus ``chtc_*``): ``MetricsSnapshot``, its parts."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

from service.contracts.snapshots import ChtcSnapshot

__all__ = ["CoreMetrics", "FilterMetrics", "HistogramData", "MetricsSnapshot", "OutletMetrics"]


@dataclass(frozen=True, kw_only=True)
class HistogramData:
    """A cumulative histogram as Prometheus wants it: counts[i] = observations <= upper_bounds[i]."""

    upper_bounds: tuple[float, ...]  # ascending, without +Inf
    counts: tuple[int, ...]  # cumulative, same length as upper_bounds
    count: int  # total (the +Inf bucket)
    sum: float


@dataclass(frozen=True, kw_only=True)
class FilterMetrics:
    """The live state's Kalman filter (docs/design/estimator.md): the last sample's normalised innovation
    squared ``nis`` over ``dof`` used channels (E[nis] = dof under a consistent filter), the NIS window's Σ
    NIS / Σ dof (``window_ratio``, ≈ 1 when consistent), its verdict ("filling", "ok", "high", "low"), whether
    the state has ``converged`` since the (re)start and whether the NIS has been above its band long enough to
    be reported (``inconsistent``)."""

    nis: float
    dof: int
    window_ratio: float | None
    verdict: str
    converged: bool
    inconsistent: bool


@dataclass(frozen=True, kw_only=True)
class CoreMetrics:
    """The core thread: ``wait_s`` each event's wait in its queue [s]; ``queued`` events now; ``lag_s`` how
    long the oldest waiting sample has waited [s]; ``dropped`` samples (queue full) and ``handled`` events."""

    wait_s: HistogramData
    queued: int
    lag_s: float
    dropped: int
    handled: int


@dataclass(frozen=True, kw_only=True)
class OutletMetrics:
    """An outlet's delivery counters since start (``chtc_outlet_*``): messages ``sent``, ``dropped`` (its
    buffer full), ``buffered`` now, ``reconnects`` (connections after the first), ``connect_failures``
    (refused tries), ``connected`` now (None: an outlet without a connection of its own, a server) and the
    requests a server ``refused``, by reason (OPC UA: ``Write``, ``Call``, ``BadTooManySessions``, ...)."""

    sent: int = 0
    dropped: int = 0
    buffered: int = 0
    reconnects: int = 0
    connect_failures: int = 0
    connected: bool | None = None
    refused: Mapping[str, int] = field(default_factory=dict)


@dataclass(frozen=True, kw_only=True)
class MetricsSnapshot:
    """Numbers the service exposes; the API turns them into Prometheus metrics (``chtc_*``)."""

    modbus_poll_latency_s: HistogramData  # successful polls' round trips (the driver's own timing)
    # outcomes (every poll / frame has exactly one); events are counted separately below
    modbus_polls_total: Mapping[str, int]  # "ok", "device_timeout", "short_reply", "link_down", ...
    can_frames_total: Mapping[str, int]  # "ok", "unknown_frame_id", "wrong_dlc", ...
    channel_age_s: Sequence[float | None]  # 32; seconds since the channel's last good value, None = never
    channel_quality: Sequence[str]  # 32; current Quality value per channel
    identifications_total: Mapping[str, int]  # by outcome: "ok", "failed", "insufficient-data"
    identification_duration_s: HistogramData
    last_fit: float | None
    last_rmse_c: float | None
    db_pending_rows: int = 0
    db_errors_total: int = 0
    db_write_s: HistogramData | None = None  # each batch's write and commit (None: no database writer)
    reconnects_total: Mapping[str, int] = field(default_factory=dict)  # by device
    modbus_events_total: Mapping[str, int] = field(default_factory=dict)  # "new_samples", "restarts", ...
    can_events_total: Mapping[str, int] = field(default_factory=dict)  # "counter_gaps", "faults", silence...
    chtc: ChtcSnapshot | None = None  # the current H, CIs, status, usable_for_compensation (None: none yet)
    build_version: str = ""  # package version (chtc_build_info)
    model_version: str | None = None
    filter: FilterMetrics | None = None  # None before the live state started
    # docs/design/threading.md: the event loop's lag (None: not measured), its largest of the last window [s];
    # the core thread (None: the core runs inline): how long events waited for it, its backlog now
    loop_lag_s: HistogramData | None = None
    loop_lag_recent_max_s: float | None = None
    core: CoreMetrics | None = None
    growth_terms_computed: int = 0  # /compensation's condition terms computed (cache misses) and their CPU
    growth_terms_cpu_s: float = 0.0
    outlets: Mapping[str, OutletMetrics] = field(default_factory=dict)  # by outlet name (those counting)
