"""Several spindles in one instance (issue 29, item 5; docs/design/fleet.md).

``Host(settings, ...)`` runs one :class:`service.host.runtime.Runtime` per ``[[spindles]]`` entry
(``Settings.per_spindle()``), each with its own devices, acquisition, core, writer and verdicts, and shares
what one process can share:

- the **reduced model** and the **growth operators**: built once per geometry (``ModelRef``) and handed to
  every spindle of that geometry;
- one **identification pool** (``service.identify.pool.WorkerPool``, ``[engine] identification_workers``
  processes, one per core by default) instead of a worker process per spindle, fair in the order asked;
- one **database engine** pair (``SharedDatabase``: reads, writes), with spindle-bound sessions; the
  database-wide retention pass runs once, from the first spindle that starts;
- one **event-loop lag monitor** (``service.shell.looplag``): the spindles share the loop, so one
  measurement serves every spindle's ``/healthz`` (``event_loop``) and ``/metrics``;
- one **REST server**: the ``"rest_fleet"`` outlet (``api.fleet``) answers ``/api/v1/spindles`` and
  ``/api/v1/spindles/{id}/…``, one ``/metrics`` labelled by spindle, and today's paths when it hosts one.

**Isolation.** A spindle whose configuration cannot be used (its register map, its CAN interface, its
geometry) or whose start fails is reported (``failed``: id → reason, ``/api/v1/spindles``) and the others
start; a device fault is the affected spindle's alone (its driver backs off; the others' loops and threads
never wait on it). Every spindle's failure after start is in its own health.

- one **OPC UA server** (``[opcua] enabled``): ``service.serve.opcua.outlet.HostedOpcUa``, one object per
  running spindle named by its id, of one type, each fed by its spindle's views (issue 43);
- one **Sparkplug B edge node** (``[mqtt] enabled``): ``service.serve.mqtt.hosted.HostedMqtt``, one device
  per running spindle named by its id (or its ``spindles[i].mqtt.device_id``), each fed by its spindle's
  views: one NBIRTH, a DBIRTH per spindle, DDATA per spindle, NDEATH as the Will (issue 43). In JSON mode one
  connection per spindle (``{topic_prefix}/{device}/...``).
"""

from __future__ import annotations

import asyncio
import contextlib
import os
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from service.errors import ServiceError
from service.modelload import LoadedModel, ModelRef, load_model
from service.serve.outlet import Outlet, OutletContext, OutletFactory, load_factory

if TYPE_CHECKING:
    from service.contracts.metrics import OutletMetrics
    from service.estimate.growth import GrowthContext
    from service.host.persistence import SharedDatabase
    from service.host.runtime import CanDevice, DaqDevice, Runtime, ScaledClock
    from service.identify.pool import WorkerPool
    from service.serve.mqtt.hosted import HostedMqtt
    from service.serve.opcua.outlet import HostedOpcUa
    from service.settings import Settings
    from service.shell.looplag import LoopLagMonitor

__all__ = ["DeviceFactory", "Host", "HostError", "HostedSpindle"]

# the spindle's devices from its settings (``chtc run``: the Modbus and CAN drivers); may raise for a bad
# register map or CAN interface, which fails that spindle only
DeviceFactory = Callable[["Settings"], tuple["DaqDevice", "CanDevice"]]


class HostError(ServiceError, RuntimeError):
    """The instance cannot host these spindles (a setting it does not support with ``[[spindles]]``)."""


@dataclass(frozen=True, kw_only=True)
class HostedSpindle:
    """One spindle of the host: its settings and running service, or why it is not running."""

    id: str
    description: str
    settings: Settings
    runtime: Runtime | None
    error: str | None = None

    @property
    def service(self) -> object | None:
        return None if self.runtime is None else self.runtime.service


@dataclass(kw_only=True)
class Host:
    """See the module docstring. ``await start()``, ``await stop()``."""

    settings: Settings
    clock: ScaledClock
    devices: DeviceFactory
    on_event: Callable[[str], None]
    migrate: bool = True
    simulated_time: bool = False
    outlets: Mapping[str, OutletFactory] | None = None  # name -> factory (default: OUTLETS)
    spindles: dict[str, HostedSpindle] = field(default_factory=dict)  # in the order of the file
    models: dict[ModelRef, LoadedModel] = field(default_factory=dict)
    growth_contexts: dict[ModelRef, GrowthContext | None] = field(default_factory=dict)  # None: unavailable
    pool: WorkerPool | None = None
    db: SharedDatabase | None = None
    rest: Outlet | None = None
    opcua: HostedOpcUa | None = None
    mqtt: HostedMqtt | None = None
    loop_lag: LoopLagMonitor | None = None
    _loop_lag_task: asyncio.Task[None] | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        if self.settings.spindles and self.settings.mqtt.enabled and self.settings.mqtt.device_id is not None:
            raise HostError(
                "mqtt.device_id names the device of one spindle; with [[spindles]] each device is named by "
                "its spindles[i].id or spindles[i].mqtt.device_id (unset mqtt.device_id)"
            )
        if self.settings.spindles and self.settings.opcua.enabled and self.settings.opcua.spindle is not None:
            raise HostError(
                "opcua.spindle names the object of one spindle; with [[spindles]] each object is named by "
                "its spindles[i].id (unset opcua.spindle)"
            )

    @property
    def failed(self) -> dict[str, str]:
        return {sid: h.error for sid, h in self.spindles.items() if h.error is not None}

    def outlet_metrics(self) -> dict[str, OutletMetrics]:
        """The host's own outlets' counters for ``/metrics`` (the OPC UA server's refusals, the MQTT
        connections' deliveries), by outlet name; a spindle's own ``/metrics`` has none of them."""
        return {o.name: o.outlet_metrics() for o in (self.opcua, self.mqtt) if o is not None}

    def model(self, settings: Settings) -> LoadedModel:
        """The reduced model of ``settings``' geometry: loaded once, shared by the spindles that have it."""
        ref = ModelRef.from_settings(settings)
        if ref not in self.models:
            self.models[ref] = load_model(ref, progress=lambda m: self.on_event(f"model: {m}"))
        return self.models[ref]

    def growth_context(self, model: LoadedModel) -> GrowthContext | None:
        """The growth operators of ``model``'s geometry (about 20 MiB and 0.7 s each): built once, shared by
        its spindles (read-only; a commissioned spindle derives its own calibrated copy of the operators).
        None when the geometry has no usable mechanics: each spindle then reports why, as alone."""
        from service.estimate.growth import build_context

        if model.ref not in self.growth_contexts:
            try:
                ctx = build_context(model.spec, model.fe, basis=model.rom.basis)
            except Exception as err:
                self.on_event(f"growth model of {model.version} unavailable: {type(err).__name__}: {err}")
                ctx = None
            self.growth_contexts[model.ref] = ctx
        return self.growth_contexts[model.ref]

    async def start(self, *, api: bool = True) -> None:
        """Open the shared parts, then start each spindle (a failing one is reported, the rest start)."""
        from service.host.persistence import SharedDatabase
        from service.host.runtime import loop_lag_monitor
        from service.identify.pool import WorkerPool

        s = self.settings
        self.loop_lag = loop_lag_monitor(s)
        self._loop_lag_task = asyncio.ensure_future(self.loop_lag.run())
        workers = s.engine.identification_workers or max(1, os.cpu_count() or 1)
        self.pool = WorkerPool(workers=workers)
        self.db = await asyncio.to_thread(SharedDatabase.open, s.database)
        for spindle in s.per_spindle():
            # the host serves OPC UA and MQTT for every spindle (``_start_opcua``, ``_start_mqtt``), not each
            # spindle for itself
            off = {
                "opcua": spindle.opcua.model_copy(update={"enabled": False}),
                "mqtt": spindle.mqtt.model_copy(update={"enabled": False}),
            }
            await self._start_spindle(spindle.model_copy(update=off))
        if self.models:  # every pool process loads every geometry now (memory at start, first jobs quick)
            await self.pool.warm(list(self.models))
        if s.opcua.enabled:
            await self._start_opcua()
        if s.mqtt.enabled:
            await self._start_mqtt()
        started = len(self.spindles) - len(self.failed)
        self.on_event(
            f"host: {started} of {len(self.spindles)} spindles running, {len(self.models)} model(s), "
            f"{workers} identification process(es)"
        )
        if api:
            factory = (self.outlets or {}).get("rest_fleet") or load_factory("rest_fleet")
            ctx = OutletContext(
                settings=s,
                service=self,
                clock=self.clock,
                simulated=self.simulated_time,
                speedup=self.clock.speedup,
                on_event=self.on_event,
            )
            self.rest = factory(ctx)
            await self.rest.start()

    async def _start_opcua(self) -> None:
        """One OPC UA server with an object per running spindle, each subscribed to its spindle's views."""
        from service.serve.opcua.outlet import HostedOpcUa

        services = self._running()
        if not services:
            return
        self.opcua = HostedOpcUa(self.settings, services, clock=self.clock)
        await self.opcua.start()
        for sid, service in services.items():
            service.subscribe(self.opcua.feeds[sid])
        self.on_event(f"OPC UA server at {self.opcua.server.endpoint}: {len(services)} spindle object(s)")

    def _running(self) -> dict[str, Any]:
        """The running spindles' services, by id, in the order of the file."""
        return {
            sid: h.runtime.service
            for sid, h in self.spindles.items()
            if h.runtime is not None and h.runtime.service is not None
        }

    async def _start_mqtt(self) -> None:
        """One Sparkplug edge node with a device per running spindle (JSON: a connection per spindle), each
        subscribed to its spindle's views."""
        from service.serve.mqtt.hosted import HostedMqtt

        services = self._running()
        if not services:
            return
        spindles = {sid: self.spindles[sid].settings for sid in services}
        self.mqtt = HostedMqtt(self.settings, spindles, clock=self.clock, on_event=self.on_event)
        await self.mqtt.start()
        for sid, service in services.items():
            service.subscribe(self.mqtt.feeds[sid])
        m = self.settings.mqtt
        where = f"{m.group_id}/{m.edge_node_id}" if m.mode == "sparkplug" else m.topic_prefix
        self.on_event(f"MQTT ({m.mode}) to {m.host}:{m.port}, {where}: {len(services)} spindle device(s)")

    async def _start_spindle(self, s: Settings) -> None:
        from service.host.runtime import Runtime

        sid = s.spindle.id
        # the first spindle that starts migrates the database (once) and runs its retention pass (it covers
        # every spindle); a spindle that failed before does not leave the schema unmigrated
        lead = not any(h.runtime is not None for h in self.spindles.values())

        def say(msg: str) -> None:
            self.on_event(f"[{sid}] {msg}")

        runtime: Runtime | None = None
        try:
            model = await asyncio.to_thread(self.model, s)
            growth = await asyncio.to_thread(self.growth_context, model)
            daq, can = self.devices(s)
            assert self.pool is not None and self.db is not None
            runtime = Runtime(
                settings=s,
                clock=self.clock,
                on_event=say,
                migrate=self.migrate and lead,  # one upgrade per database; the others check the revision
                model=model,
                worker=self.pool.lease(model.ref, timeout_s=s.identification.timeout_s),
                shared_db=self.db,
                retention=lead,
                growth_context=growth,
                loop_lag=self.loop_lag,
                simulated_time=self.simulated_time,
            )
            await runtime.start(daq=daq, can=can, api=False)
        except Exception as err:  # this spindle only: the others start regardless
            text = f"{type(err).__name__}: {err}"
            say(f"not started: {text}")
            if runtime is not None:
                with contextlib.suppress(Exception):
                    await runtime.stop()
            self.spindles[sid] = HostedSpindle(
                id=sid, description=s.spindle.description, settings=s, runtime=None, error=text
            )
            return
        self.spindles[sid] = HostedSpindle(
            id=sid, description=s.spindle.description, settings=s, runtime=runtime
        )

    async def wait_api(self, timeout_s: float = 20.0) -> None:
        """Wait until the REST server accepts connections (raises TimeoutError)."""
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout_s
        while not bool(getattr(self.rest, "started", False)):
            if loop.time() > deadline:
                raise TimeoutError(f"API server not up within {timeout_s:.0f} s")
            await asyncio.sleep(0.05)

    @property
    def url(self) -> str:
        return f"http://{self.settings.api.host}:{self.settings.api.port}/"

    async def stop(self) -> None:
        """Stop the REST server, then every spindle, then the shared pool and engines."""
        if self.rest is not None:
            with contextlib.suppress(Exception):
                await self.rest.close()
        if self.mqtt is not None:
            for h in self.spindles.values():
                device = self.mqtt.feeds.get(h.id)
                if device is not None and h.runtime is not None and h.runtime.service is not None:
                    h.runtime.service.unsubscribe(device)
            with contextlib.suppress(Exception):
                await self.mqtt.close()
        if self.opcua is not None:
            for h in self.spindles.values():
                feed = self.opcua.feeds.get(h.id)
                if feed is not None and h.runtime is not None and h.runtime.service is not None:
                    h.runtime.service.unsubscribe(feed)
            with contextlib.suppress(Exception):
                await self.opcua.close()
        for hosted in reversed(list(self.spindles.values())):
            if hosted.runtime is not None:
                try:
                    await hosted.runtime.stop()
                except Exception as err:  # stop the rest regardless
                    self.on_event(f"[{hosted.id}] shutdown failed: {type(err).__name__}: {err}")
        if self.pool is not None:
            await asyncio.to_thread(self.pool.close)
        if self.db is not None:
            await asyncio.to_thread(self.db.close)
        task, self._loop_lag_task = self._loop_lag_task, None
        if task is not None:
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)
