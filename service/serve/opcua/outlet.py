"""The OPC UA outlet (``service.serve.outlet``): ``opcua_outlet`` is the ``"opcua"`` entry of ``OUTLETS``.

``start()`` starts the server's thread (``service.serve.opcua.server``) and waits for it off the event loop;
``on_view`` puts the newest reader into the server's slot (no work on the loop); ``close()`` stops the thread.
The methods (``[opcua] methods = true``) call the service's own requests, as ``POST /identifications`` and
``POST /sensors/baseline`` do.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable, Mapping
from datetime import datetime
from typing import TYPE_CHECKING, Any

from service.contracts.metrics import OutletMetrics
from service.serve.opcua.nodes import variables
from service.serve.opcua.server import Methods, OpcUaServer

if TYPE_CHECKING:
    from service.contracts.snapshots import IdentificationJob, OffsetBaseline
    from service.serve.outlet import OutletContext
    from service.serve.reader import ViewReader
    from service.settings import Settings

__all__ = ["HostedOpcUa", "OpcUaOutlet", "opcua_outlet"]


class OpcUaOutlet:
    name = "opcua"

    def __init__(self, ctx: OutletContext) -> None:
        s = ctx.settings
        cfg = s.opcua.for_spindle(s.spindle.id)  # NodeIds named after the spindle unless set
        service = ctx.service
        n_sensors = len(service.core.model.spec.sensors) if hasattr(service, "core") else 32
        bad_after_s = (
            cfg.bad_after_s if cfg.bad_after_s is not None else 60.0 * s.compensation.max_open_loop_min
        )
        methods = _methods(service) if cfg.methods else None
        self.server = OpcUaServer(
            cfg,
            variables=variables(n_sensors),
            clock=ctx.clock,
            bad_after_s=bad_after_s,
            n_sensors=n_sensors,
            methods=methods,
        )
        self.ctx = ctx

    async def start(self) -> None:
        await asyncio.to_thread(self.server.start)
        self.ctx.on_event(f"OPC UA server at {self.server.endpoint}")

    def on_view(self, reader: ViewReader) -> None:
        self.server.offer(reader)

    async def close(self) -> None:
        await asyncio.to_thread(self.server.stop)

    def outlet_metrics(self) -> OutletMetrics:
        """For ``/metrics`` (``service.serve.interface.CountedOutlet``): the requests refused, by reason."""
        return OutletMetrics(refused=self.server.refusals.counts())


class _SpindleFeed:
    """One hosted spindle's subscription: its views go to its object on the host's server."""

    name = "opcua"

    def __init__(self, server: OpcUaServer, spindle: str) -> None:
        self.server = server
        self.spindle = spindle

    async def start(self) -> None:
        return None

    def on_view(self, reader: ViewReader) -> None:
        self.server.offer(reader, self.spindle)

    async def close(self) -> None:
        return None


class HostedOpcUa:
    """One OPC UA server for the spindles of a host (``[[spindles]]``): one object per spindle, named by its
    id, of the one type (``SpindleThermalModelType``), each fed by its spindle's views (``feeds``: subscribe
    each to its spindle's service) and, with ``methods = true``, with its own methods."""

    name = "opcua"

    def __init__(
        self, settings: Settings, services: Mapping[str, Any], *, clock: Callable[[], datetime]
    ) -> None:
        ids = list(services)
        cfg = settings.opcua.for_spindle(ids[0])  # the endpoint and security; the objects are the ids
        bad_after_s = (
            cfg.bad_after_s if cfg.bad_after_s is not None else 60.0 * settings.compensation.max_open_loop_min
        )
        n_sensors = max(
            (len(svc.core.model.spec.sensors) for svc in services.values() if hasattr(svc, "core")),
            default=32,
        )
        methods = None
        if cfg.methods:
            methods = {sid: _methods(svc) for sid, svc in services.items()}
        self.server = OpcUaServer(
            cfg,
            variables=variables(n_sensors),
            clock=clock,
            bad_after_s=bad_after_s,
            n_sensors=n_sensors,
            methods=methods,
            spindles=ids,
        )
        self.feeds = {sid: _SpindleFeed(self.server, sid) for sid in ids}

    async def start(self) -> None:
        await asyncio.to_thread(self.server.start)

    async def close(self) -> None:
        await asyncio.to_thread(self.server.stop)

    def outlet_metrics(self) -> OutletMetrics:
        return OutletMetrics(refused=self.server.refusals.counts())


def _methods(service: Any) -> Methods:
    return Methods(
        start_identification=lambda reason: _job_text(service.request_identification(reason)),
        take_sensor_baseline=lambda: _baseline_text(service.request_baseline()),
    )


def _job_text(job: IdentificationJob) -> str:
    return f"{job.job_id} {job.state.value}"


def _baseline_text(b: OffsetBaseline) -> str:
    return f"baseline {b.t_from.isoformat()} .. {b.t_to.isoformat()} ({b.samples} samples)"


def opcua_outlet(ctx: OutletContext) -> OpcUaOutlet:
    """The ``"opcua"`` entry of ``service.serve.outlet.OUTLETS``."""
    return OpcUaOutlet(ctx)
