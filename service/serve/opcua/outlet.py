"""The OPC UA outlet (``service.serve.outlet``): ``opcua_outlet`` is the ``"opcua"`` entry of ``OUTLETS``.

``start()`` starts the server's thread (``service.serve.opcua.server``) and waits for it off the event loop;
``on_view`` puts the newest reader into the server's slot (no work on the loop); ``close()`` stops the thread.
The methods (``[opcua] methods = true``) call the service's own requests, as ``POST /identifications`` and
``POST /sensors/baseline`` do.
"""

from __future__ import annotations

import asyncio
from typing import TYPE_CHECKING

from service.serve.opcua.nodes import variables
from service.serve.opcua.server import Methods, OpcUaServer

if TYPE_CHECKING:
    from service.contracts.snapshots import IdentificationJob, OffsetBaseline
    from service.serve.outlet import OutletContext
    from service.serve.reader import ViewReader

__all__ = ["OpcUaOutlet", "opcua_outlet"]


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
        methods = None
        if cfg.methods:
            methods = Methods(
                start_identification=lambda reason: _job_text(service.request_identification(reason)),
                take_sensor_baseline=lambda: _baseline_text(service.request_baseline()),
            )
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


def _job_text(job: IdentificationJob) -> str:
    return f"{job.job_id} {job.state.value}"


def _baseline_text(b: OffsetBaseline) -> str:
    return f"baseline {b.t_from.isoformat()} .. {b.t_to.isoformat()} ({b.samples} samples)"


def opcua_outlet(ctx: OutletContext) -> OpcUaOutlet:
    """The ``"opcua"`` entry of ``service.serve.outlet.OUTLETS``."""
    return OpcUaOutlet(ctx)
