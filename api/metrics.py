"""Prometheus exposition: a per-app ``CollectorRegistry`` with the API's own request-latency histogram and a
collector that turns the service's :class:`service.interface.MetricsSnapshot` into ``chtc_*`` families at
scrape time (the service exposes numbers; the API exports them).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from typing import Any

from prometheus_client import CollectorRegistry, Histogram
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, HistogramMetricFamily, Metric
from prometheus_client.registry import Collector

from service.interface import LATENCY_BUCKETS_S, ChtcService, HistogramData

REQUEST_BUCKETS_S = (0.0005, 0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.25, 0.5, 1.0)


def _hist(name: str, doc: str, h: HistogramData) -> HistogramMetricFamily:
    buckets = [(repr(float(ub)), c) for ub, c in zip(h.upper_bounds, h.counts, strict=True)]
    buckets.append(("+Inf", h.count))
    return HistogramMetricFamily(name, doc, buckets=buckets, sum_value=h.sum)


def _counter(name: str, doc: str, label: str, values: dict[str, int] | Any) -> CounterMetricFamily:
    fam = CounterMetricFamily(name, doc, labels=[label])
    for key, value in sorted(dict(values).items()):
        fam.add_metric([key], value)
    return fam


class ServiceCollector(Collector):
    """Reads ``service.metrics()`` at each scrape."""

    def __init__(self, service: ChtcService) -> None:
        self._service = service

    def collect(self) -> Iterator[Metric]:
        m = self._service.metrics()
        yield _hist("chtc_modbus_poll_latency_seconds", "Modbus DAQ poll round trip", m.modbus_poll_latency_s)
        yield _counter("chtc_modbus_polls", "Modbus polls by outcome", "outcome", m.modbus_polls_total)
        yield _counter("chtc_can_frames", "CAN frames by outcome", "outcome", m.can_frames_total)
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


class ApiMetrics:
    """The app's registry plus the request-latency histogram."""

    def __init__(self, service: ChtcService) -> None:
        self.registry = CollectorRegistry(auto_describe=False)
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

    def __init__(self, app: Callable[..., Any], metrics: ApiMetrics, prefix: str = "") -> None:
        self.app = app
        self.metrics = metrics
        self.prefix = prefix

    async def __call__(
        self, scope: dict[str, Any], receive: Callable[..., Any], send: Callable[..., Any]
    ) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        start = time.perf_counter()
        status = [500]

        async def send_wrapper(message: dict[str, Any]) -> None:
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


__all__ = ["LATENCY_BUCKETS_S", "ApiMetrics", "RequestTimer"]
