"""Prometheus exposition: a per-app ``CollectorRegistry`` with the API's own request-latency histogram and a
collector that turns the service's :class:`service.contracts.metrics.MetricsSnapshot` into ``chtc_*`` families
at
scrape time (the service exposes numbers; the API exports them).
"""

from __future__ import annotations

import math
import time
from collections.abc import Iterator, Mapping

from prometheus_client import CollectorRegistry, Histogram
from prometheus_client.core import (
    CounterMetricFamily,
    GaugeMetricFamily,
    HistogramMetricFamily,
    InfoMetricFamily,
    Metric,
)
from prometheus_client.registry import Collector
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from service.contracts.metrics import FilterMetrics, HistogramData, MetricsSnapshot, OutletMetrics
from service.contracts.snapshots import ChtcSnapshot, CompensationSnapshot
from service.contracts.verdict import ChtcStatus
from service.errors import ServiceError
from service.serve.histogram import LATENCY_BUCKETS_S
from service.serve.interface import ChtcService

REQUEST_BUCKETS_S = (0.0005, 0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.25, 0.5, 1.0)


def _hist(name: str, doc: str, h: HistogramData) -> HistogramMetricFamily:
    buckets = [(repr(float(ub)), c) for ub, c in zip(h.upper_bounds, h.counts, strict=True)]
    buckets.append(("+Inf", h.count))
    return HistogramMetricFamily(name, doc, buckets=buckets, sum_value=h.sum)


def _counter(name: str, doc: str, label: str, values: Mapping[str, int]) -> CounterMetricFamily:
    fam = CounterMetricFamily(name, doc, labels=[label])
    for key, value in sorted(dict(values).items()):
        fam.add_metric([key], value)
    return fam


STATUSES = tuple(s.value for s in ChtcStatus)


def _chtc_gauges(snap: ChtcSnapshot | None) -> Iterator[Metric]:
    """H1-H7 with their 95 % CI bounds (W/(m²·K)), identified / at-bound flags, the status (one-hot) and
    ``usable_for_compensation``; nothing before the first identification."""
    if snap is None:
        return
    zones = list(snap.zones)
    bound = snap.at_bound if snap.at_bound is not None else [False] * len(zones)
    for name, doc, values in (
        ("chtc_h_w_m2k", "current H, W/(m²·K)", snap.h),
        ("chtc_h_ci95_lo_w_m2k", "lower 95 % CI bound of H, W/(m²·K)", snap.ci95_lo),
        ("chtc_h_ci95_hi_w_m2k", "upper 95 % CI bound of H, W/(m²·K)", snap.ci95_hi),
        ("chtc_h_identified", "1 if H is identified (CI narrow enough, not at a bound)", snap.identified),
        ("chtc_h_at_bound", "1 if H is on a bound of the search box", bound),
    ):
        fam = GaugeMetricFamily(name, doc, labels=["zone"])
        for zone, v in zip(zones, values, strict=True):
            if math.isfinite(float(v)):
                fam.add_metric([zone], float(v))
        yield fam
    status = GaugeMetricFamily("chtc_status", "1 for the current /chtc status", labels=["status"])
    for st in STATUSES:
        status.add_metric([st], 1.0 if str(snap.status) == st else 0.0)
    yield status
    yield GaugeMetricFamily(
        "chtc_usable_for_compensation",
        "1 if a controller may apply the current H (/chtc usable_for_compensation)",
        value=1.0 if snap.usable_for_compensation else 0.0,
    )
    why = GaugeMetricFamily(
        "chtc_not_usable_reason", "1 for the code of /chtc reason while not usable", labels=["code"]
    )
    if snap.verdict.reason is not None:
        why.add_metric([snap.verdict.reason.value], 1.0)
    yield why


def _growth_gauges(snap: CompensationSnapshot | None) -> Iterator[Metric]:
    """``/compensation`` as gauges: growth, 95 % CI half-width, status (none before the first estimate)."""
    if snap is None:
        return
    g = snap.growth
    for name, doc, key in (
        ("chtc_growth_um", "thermal growth at the spindle nose now, µm (/compensation)", "um"),
        ("chtc_growth_ci95_half_width_um", "half-width of the growth's 95 % CI, µm", "half"),
    ):
        fam = GaugeMetricFamily(name, doc, labels=["direction"])
        for direction, v in (("axial", g.axial), ("radial", g.radial)):
            value = v.um if key == "um" else 0.5 * (v.ci95_um[1] - v.ci95_um[0])
            if math.isfinite(value):
                fam.add_metric([direction], value)
        yield fam
    steady = GaugeMetricFamily(
        "chtc_growth_steady_um", "steady-state growth if the condition holds, µm", labels=["direction"]
    )
    steady.add_metric(["axial"], g.forecast.steady_axial.um)
    steady.add_metric(["radial"], g.forecast.steady_radial.um)
    yield steady
    status = GaugeMetricFamily(
        "chtc_growth_status", "1 for the current /compensation status", labels=["status"]
    )
    for st in STATUSES:
        status.add_metric([st], 1.0 if str(snap.status) == st else 0.0)
    yield status
    yield GaugeMetricFamily(
        "chtc_compensation_usable",
        "1 if a controller may apply the growth now (/compensation usable_for_compensation)",
        value=1.0 if snap.verdict.usable else 0.0,
    )
    why = GaugeMetricFamily(
        "chtc_compensation_not_usable_reason",
        "1 for the /compensation reason code while not usable",
        labels=["code"],
    )
    if snap.verdict.reason is not None:
        why.add_metric([snap.verdict.reason.value], 1.0)
    yield why


def reason_code(reason: str) -> str:
    """A ``/readyz`` reason ``"daq_no_good_data: ..."`` -> ``"daq_no_good_data"`` (bounded labels; the
    /chtc and /compensation verdicts carry typed codes)."""
    return reason.split(":", 1)[0].strip() or "unknown"


def _readiness(service: ChtcService) -> Iterator[Metric]:
    """``/readyz`` as gauges: ready 0/1 and one series per reason code (``can_no_good_data`` ...)."""
    r = service.ready()
    yield GaugeMetricFamily("chtc_ready", "1 if /readyz answers 200", value=1.0 if r.ready else 0.0)
    fam = GaugeMetricFamily("chtc_not_ready_reason", "1 for each /readyz reason code", labels=["code"])
    for code in sorted({reason_code(x) for x in r.reasons}):
        fam.add_metric([code], 1.0)
    yield fam


class ServiceCollector(Collector):
    """Reads ``service.metrics()`` at each scrape."""

    def __init__(self, service: ChtcService) -> None:
        self._service = service

    def collect(self) -> Iterator[Metric]:
        m = self._service.metrics()
        lat = m.modbus_poll_latency_s
        yield _hist("chtc_modbus_poll_latency_seconds", "Modbus DAQ poll round trip (successful polls)", lat)
        yield _counter(
            "chtc_modbus_polls", "Modbus polls by outcome, one per poll", "outcome", m.modbus_polls_total
        )
        yield _counter("chtc_modbus_events", "Modbus DAQ events", "event", m.modbus_events_total)
        yield _counter(
            "chtc_can_frames", "CAN frames by outcome, one per frame", "outcome", m.can_frames_total
        )
        yield _counter("chtc_can_events", "CAN events: gaps, faults, silence", "event", m.can_events_total)
        yield from _chtc_gauges(m.chtc)
        try:
            growth = self._service.compensation()
        except ServiceError:  # no growth model (its cause: /compensation, 503)
            growth = None
        yield from _growth_gauges(growth)
        yield from _readiness(self._service)
        yield InfoMetricFamily(
            "chtc_build",
            "package and model version",
            value={"version": m.build_version, "model_version": m.model_version or ""},
        )
        yield _counter("chtc_reconnects", "device reconnects", "device", m.reconnects_total)
        yield _counter(
            "chtc_identifications", "identifications by outcome", "outcome", m.identifications_total
        )
        yield _hist(
            "chtc_identification_duration_seconds", "identification wall time", m.identification_duration_s
        )
        age = GaugeMetricFamily(
            "chtc_channel_age_seconds", "age of the channel's last good value", labels=["channel"]
        )
        for i, a in enumerate(m.channel_age_s, start=1):
            if a is not None:
                age.add_metric([str(i)], a)
        yield age
        bad = GaugeMetricFamily(
            "chtc_channel_ok", "1 if the channel's quality is ok", labels=["channel", "quality"]
        )
        for i, q in enumerate(m.channel_quality, start=1):
            bad.add_metric([str(i), q], 1.0 if q == "ok" else 0.0)
        yield bad
        for name, doc, value in (
            ("chtc_identification_fit", "fit = 1/(1+f) of the last identification", m.last_fit),
            ("chtc_identification_rmse_celsius", "RMSE of the last identification, °C", m.last_rmse_c),
        ):
            if value is not None:
                yield GaugeMetricFamily(name, doc, value=value)
        yield GaugeMetricFamily(
            "chtc_db_pending_rows", "rows buffered for the database", value=m.db_pending_rows
        )
        yield CounterMetricFamily("chtc_db_errors", "database write errors", value=m.db_errors_total)
        if m.db_write_s is not None:
            yield _hist(
                "chtc_db_write_seconds", "database writes: one batch written and committed, s", m.db_write_s
            )
        yield from _filter_gauges(m.filter)
        yield from _loop_metrics(m)
        yield from outlet_families(m.outlets)


def outlet_families(outlets: Mapping[str, OutletMetrics]) -> Iterator[Metric]:
    """The outlets' deliveries (MQTT: messages sent and dropped, the buffer, reconnects; integration.md)."""
    if not outlets:
        return
    sent = CounterMetricFamily(
        "chtc_outlet_messages",
        "outlet messages by result (sent, dropped: buffer full)",
        labels=["outlet", "result"],
    )
    families: dict[str, CounterMetricFamily | GaugeMetricFamily] = {
        "reconnects": CounterMetricFamily(
            "chtc_outlet_reconnects", "connections after the first", labels=["outlet"]
        ),
        "connect_failures": CounterMetricFamily(
            "chtc_outlet_connect_failures", "connect tries refused or failed", labels=["outlet"]
        ),
        "buffered": GaugeMetricFamily(
            "chtc_outlet_buffered", "messages waiting to be sent", labels=["outlet"]
        ),
    }
    connected = GaugeMetricFamily("chtc_outlet_connected", "1 while connected", labels=["outlet"])
    refused = CounterMetricFamily(
        "chtc_outlet_refused", "requests a server outlet refused, by reason", labels=["outlet", "reason"]
    )
    for name, o in sorted(outlets.items()):
        for reason, count in sorted(o.refused.items()):
            refused.add_metric([name, reason], count)
        sent.add_metric([name, "sent"], o.sent)
        sent.add_metric([name, "dropped"], o.dropped)
        for key, fam in families.items():
            fam.add_metric([name], getattr(o, key))
        if o.connected is not None:
            connected.add_metric([name], 1.0 if o.connected else 0.0)
    yield sent
    yield from families.values()
    yield connected
    yield refused


def _loop_metrics(m: MetricsSnapshot) -> Iterator[Metric]:
    """The event loop's lag and the core thread's backlog (docs/design/threading.md)."""
    if m.loop_lag_s is not None:
        yield _hist(
            "chtc_event_loop_lag_seconds",
            "how late the event loop ran a callback it scheduled (sampled every 0.1 s)",
            m.loop_lag_s,
        )
    if m.loop_lag_recent_max_s is not None:
        yield GaugeMetricFamily(
            "chtc_event_loop_lag_recent_max_seconds",
            "largest event-loop lag of the last window (/healthz event_loop)",
            value=m.loop_lag_recent_max_s,
        )
    yield CounterMetricFamily(
        "chtc_growth_terms_computed",
        "/compensation's condition terms computed (new identification, condition or live H)",
        value=m.growth_terms_computed,
    )
    yield CounterMetricFamily(
        "chtc_growth_terms_cpu_seconds", "CPU spent computing them", value=m.growth_terms_cpu_s
    )
    c = m.core
    if c is None:
        return
    yield _hist("chtc_core_wait_seconds", "how long each event waited for the core thread", c.wait_s)
    yield GaugeMetricFamily("chtc_core_queued_events", "events waiting for the core thread", value=c.queued)
    yield GaugeMetricFamily(
        "chtc_core_lag_seconds",
        "how long the oldest sample not handled yet has waited for the core (service clock)",
        value=c.lag_s,
    )
    yield CounterMetricFamily(
        "chtc_core_dropped_samples", "samples dropped: the core thread's queue was full", value=c.dropped
    )
    yield CounterMetricFamily("chtc_core_handled_events", "events the core thread handled", value=c.handled)


def _filter_gauges(f: FilterMetrics | None) -> Iterator[Metric]:
    """The live state's Kalman filter: NIS of the last sample, window ratio, consistency, convergence."""
    if f is None:
        return
    yield GaugeMetricFamily(
        "chtc_filter_nis", "normalised innovation squared of the last sample (E = its dof)", value=f.nis
    )
    yield GaugeMetricFamily("chtc_filter_nis_dof", "channels used in the last sample's update", value=f.dof)
    if f.window_ratio is not None:
        yield GaugeMetricFamily(
            "chtc_filter_nis_ratio",
            "NIS window: sum NIS / sum dof (about 1 when consistent)",
            value=f.window_ratio,
        )
    yield GaugeMetricFamily(
        "chtc_filter_consistent",
        "0 while the NIS has been above its chi-squared band long enough to be reported, else 1",
        value=0.0 if f.inconsistent else 1.0,
    )
    verdict = GaugeMetricFamily(
        "chtc_filter_nis_verdict", "1 for the NIS window's verdict", labels=["verdict"]
    )
    for v in ("filling", "ok", "high", "low"):
        verdict.add_metric([v], 1.0 if f.verdict == v else 0.0)
    yield verdict
    yield GaugeMetricFamily(
        "chtc_filter_converged",
        "1 once the live state converged since the (re)start",
        value=float(f.converged),
    )


class SpindleLabelled:
    """What ``/metrics`` exposes: ``registry``'s families with ``spindle="<id>"`` on every sample (the
    ``[spindle] id``), so one Prometheus, one Grafana dashboard (deploy/grafana) and one alert rule serve many
    spindles; a sample's own ``spindle`` label, if any, is kept."""

    def __init__(self, registry: CollectorRegistry, spindle_id: str) -> None:
        self.registry = registry
        self.spindle_id = spindle_id

    def collect(self) -> Iterator[Metric]:
        for fam in self.registry.collect():
            out = Metric(fam.name, fam.documentation, fam.type, fam.unit)
            out.samples = [s._replace(labels={"spindle": self.spindle_id, **s.labels}) for s in fam.samples]
            yield out


class ApiMetrics:
    """The app's registry plus the request-latency histogram; ``exposed`` labels every sample with the
    spindle."""

    def __init__(self, service: ChtcService, spindle_id: str = "spindle1") -> None:
        self.registry = CollectorRegistry(auto_describe=False)
        self.exposed = SpindleLabelled(self.registry, spindle_id)
        self.request_latency = Histogram(
            "chtc_http_request_duration_seconds",
            "API request latency",
            ["method", "route", "status"],
            buckets=REQUEST_BUCKETS_S,
            registry=self.registry,
        )
        self.registry.register(ServiceCollector(service))


class RequestTimer:
    """Pure ASGI middleware (cheaper than BaseHTTPMiddleware) observing each request's latency by route."""

    def __init__(self, app: ASGIApp, metrics: ApiMetrics, prefix: str = "") -> None:
        self.app = app
        self.metrics = metrics
        self.prefix = prefix

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        start = time.perf_counter()
        status = [500]

        async def send_wrapper(message: Message) -> None:
            if message["type"] == "http.response.start":
                status[0] = message["status"]
            await send(message)

        try:
            await self.app(scope, receive, send_wrapper)
        finally:
            route = scope.get("route")
            path = getattr(route, "path", None) or "unmatched"
            # FastAPI >= 0.16x keeps included routes' own (prefix-less) path on the route object
            if (
                scope["path"].startswith(self.prefix)
                and not path.startswith(self.prefix)
                and path != "unmatched"
            ):
                path = self.prefix + path
            self.metrics.request_latency.labels(scope["method"], path, str(status[0])).observe(
                time.perf_counter() - start
            )


__all__ = ["LATENCY_BUCKETS_S", "ApiMetrics", "RequestTimer", "outlet_families"]
