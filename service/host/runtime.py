"""Assemble and run the whole soft sensor from ``Settings``: model, database, worker, acquisition, outlets.

The outlets (``service.serve.outlet``: REST, OPC UA, MQTT) are started after the service, by name: ``"rest"``
when ``start(api=True)``, and each other registered outlet whose settings section says ``enabled = true``
(``[opcua]``, ``[mqtt]``); their factories come from ``Runtime(outlets=...)`` or the registry
``service.serve.outlet.OUTLETS`` (so ``service`` never imports ``api``). They are closed first at ``stop()``,
in reverse order.

Used by ``chtc run`` (real devices), ``chtc demo`` (simulated devices at a speed-up) and ``chtc replay``.
``ScaledClock`` is the one clock of a run: the acquisition stamps samples with it and the service and the API
measure ages with it. At speed-up 1 it is the UTC wall clock; at speed-up S it starts at the real UTC time
and runs S times faster, so everything on the sample time axis (hold times, schedules, windows, staleness)
is in plant seconds while the wall-clock parts (device timeouts, backoff) stay real.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import socket
import sys
import time
from collections.abc import Callable, Mapping
from dataclasses import KW_ONLY, dataclass, field
from datetime import UTC, datetime, timedelta
from typing import TYPE_CHECKING, Any, Protocol

from drivers.acquisition import Acquisition, CanSource, DaqSource
from drivers.ringbuffer import RingBuffer
from service.core.config import Restored, compensation_limits, control_limits, core_config
from service.core.machine import ServiceCore
from service.host.persistence import Persistence, SharedDatabase, open_persistence
from service.identify.worker import IdentificationWorker
from service.logctx import spindle_context
from service.modelload import LoadedModel, ModelRef, load_model
from service.serve.compensation import GrowthServer, probe_tuning
from service.serve.controlled import ControlState
from service.serve.outlet import OUTLETS, Outlet, OutletContext, OutletFactory, load_factory
from service.settings import Settings
from service.shell.corethread import CoreThread, InlineRunner
from service.shell.health import HealthSource
from service.shell.looplag import LoopLagMonitor
from service.shell.service import SoftSensorService, Worker

if TYPE_CHECKING:
    import uvicorn

    from service.estimate.growth import GrowthContext

__all__ = [
    "CanDevice",
    "DaqDevice",
    "Runtime",
    "ScaledClock",
    "core_config",
    "enabled_outlets",
    "engine_parts",
    "free_port",
    "loop_lag_monitor",
]

log = logging.getLogger(__name__)


class ScaledClock:
    """UTC ``datetime`` clock running ``speedup`` times faster than the monotonic clock from ``start()``."""

    def __init__(self, speedup: float = 1.0, *, monotonic: Callable[[], float] = time.monotonic) -> None:
        if not speedup > 0:
            raise ValueError(f"speedup must be > 0, got {speedup}")
        self.speedup = float(speedup)
        self.monotonic = monotonic
        self.start()

    def start(self, at: datetime | None = None) -> None:
        """(Re)start now, reading ``at`` (default: the current UTC time; a replay uses the log's start)."""
        self._mono0 = self.monotonic()
        self._utc0 = at if at is not None else datetime.now(UTC)

    def __call__(self) -> datetime:
        return self._utc0 + timedelta(seconds=self.speedup * (self.monotonic() - self._mono0))


class DaqDevice(DaqSource, HealthSource, Protocol):
    """The DAQ driver as the runtime uses it (``drivers.modbus_daq.ModbusDaq``)."""

    async def close(self) -> None: ...


class CanDevice(CanSource, HealthSource, Protocol):
    """The CAN driver as the runtime uses it (``drivers.can_sensor.CanSpindleSensor``)."""

    async def close(self) -> None: ...


def free_port(host: str = "127.0.0.1") -> int:
    """An unused TCP port on ``host`` (for in-process simulators and the API in tests and the demo)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


def growth_server(
    model: LoadedModel,
    settings: Settings,
    restored: Restored | None = None,
    *,
    context: GrowthContext | None = None,
) -> GrowthServer:
    """``/compensation``'s server from ``Settings``: the policy's limits and the zero: the restored one, else
    ``compensation.reference_c``, else (if configured) one taken at the first start (docs/design/growth.md,
    "Reference"). ``context``: the model's growth context, built once and shared by the spindles of one
    geometry (``service.host.fleet``; default: built by the server when first needed)."""
    c = settings.compensation
    return GrowthServer(
        model,
        t_ref_c=c.reference_c,
        reference=None if restored is None else restored.reference,
        mechanics=None if restored is None else restored.mechanics,
        probes=() if restored is None else restored.probes,
        probe=probe_tuning(c),
        reference_on_first_start=c.reference_on_first_start,
        first_start_by=os_user(),
        limits=compensation_limits(c),
        context=context,
        control=control_limits(settings),
        # the gate's and the command's state from the live checkpoint (None: none stored, or an older one)
        control_state=None
        if restored is None or restored.live is None
        else ControlState.from_array(restored.live.control),
    )


def loop_lag_monitor(settings: Settings) -> LoopLagMonitor:
    """The event loop's lag monitor from ``[engine]`` (its limit and window)."""
    e = settings.engine
    return LoopLagMonitor(limit_s=e.max_loop_lag_s, window_s=e.loop_lag_window_s)


def engine_parts(settings: Settings, *, loop_lag: LoopLagMonitor | None = None) -> dict[str, Any]:
    """The shell's threading parts from ``[engine]`` (docs/design/threading.md): the core thread (or inline),
    its lag limit and the event loop's lag monitor: ``loop_lag``, run by whoever gave it (a host's, shared by
    its spindles on its one loop), else one of this shell's own, run by it."""
    e = settings.engine
    runner = CoreThread(capacity=e.core_queue_samples) if e.core_thread else InlineRunner()
    return {
        "runner": runner,
        "max_core_lag_s": e.max_core_lag_s,
        "loop_lag": loop_lag or loop_lag_monitor(settings),
        "own_loop_lag": loop_lag is None,
    }


def enabled_outlets(settings: Settings, *, api: bool, registry: Mapping[str, object] = OUTLETS) -> list[str]:
    """The outlets to start, in order: ``"rest"`` with ``api``, then every other registered one whose settings
    section (``settings.<name>``) has ``enabled`` true."""
    names = ["rest"] if api else []
    for name in registry:
        section = getattr(settings, name, None)
        if name != "rest" and bool(getattr(section, "enabled", False)):
            names.append(name)
    return names


def os_user() -> str:
    """The OS user running this process (who set a reference the service took itself), "unknown" if none."""
    import getpass

    try:
        return getpass.getuser()[:64] or "unknown"
    except (KeyError, OSError):
        return "unknown"


@dataclass(kw_only=True)
class Runtime:
    """One running soft sensor. ``await start(daq=..., can=...)``, ``await stop()``."""

    settings: Settings
    _: KW_ONLY
    clock: ScaledClock
    on_event: Callable[[str], None]
    migrate: bool = True
    model: LoadedModel | None = None
    persistence: Persistence | None = None
    service: SoftSensorService | None = None
    acquisition: Acquisition | None = None
    ring: RingBuffer | None = None  # the acquisition's (the core keeps a history of its own)
    acquisition_task: asyncio.Task[None] | None = None
    sample_clock: Callable[[], datetime] | None = None  # stamps samples (default: clock); replay: a grid
    outlets: Mapping[str, OutletFactory] | None = None  # name -> factory (default: OUTLETS, by name)
    running_outlets: dict[str, Outlet] = field(default_factory=dict)  # started, in order
    devices: tuple[DaqDevice, CanDevice] | None = None  # closed at stop()
    simulated_time: bool = False  # the clock is a simulated plant time (demo, replay): the API says so
    # an instance hosting several spindles (service.host.fleet) injects what they share: a lease of the
    # identification pool (default: a worker process of this spindle's own), the database engines (default:
    # engines of its own), and whether this spindle's persistence runs the database-wide retention pass
    worker: Worker | None = None
    shared_db: SharedDatabase | None = None
    retention: bool = True
    growth_context: GrowthContext | None = None  # the geometry's, shared (default: this spindle builds one)
    loop_lag: LoopLagMonitor | None = None  # the loop's lag monitor, run by the host (default: its own)

    @property
    def speedup(self) -> float:
        return self.clock.speedup

    def load(self, *, progress: Callable[[str], None] | None = None) -> LoadedModel:
        """Load the model (builds and caches the reduced model on the first run)."""
        if self.model is None:
            with spindle_context(self.settings.spindle.id):
                self.model = load_model(ModelRef.from_settings(self.settings), progress=progress)
        return self.model

    async def start(self, *, daq: DaqDevice, can: CanDevice, api: bool = True, acquire: bool = True) -> None:
        """Open the database, start the worker process, the acquisition and (optionally) the API server.

        ``acquire=False``: everything but the acquisition, started later by ``start_acquisition()`` (the demo
        starts its simulated devices in between, so the drivers never poll a port nobody listens on yet).
        Everything runs as this spindle (``service.logctx``): the tasks and threads started here log its id.
        """
        with spindle_context(self.settings.spindle.id):
            await self._start(daq=daq, can=can, api=api, acquire=acquire)

    async def _start(self, *, daq: DaqDevice, can: CanDevice, api: bool, acquire: bool) -> None:
        s = self.settings
        sys.setswitchinterval(s.engine.gil_switch_interval_s)  # the loop waits less for the GIL
        model = self.load()
        # in a thread: the schema check and the restore queries (~0.1 s on PostgreSQL, a migration more) would
        # hold the loop, and in a host the spindles started before this one run on it
        self.persistence = await asyncio.to_thread(
            open_persistence,
            s.database,
            migrate=self.migrate,
            on_event=self.on_event,
            clock=self.clock,
            spindle=s.spindle,
            shared=self.shared_db,
            retention=self.retention,
            log_time=self.simulated_time,
        )
        self.persistence.start_background()
        self.ring = RingBuffer(s.acquisition.ring_capacity, len(model.spec.sensors))
        core = ServiceCore(
            core_config(s),
            model=model,
            restored=self.persistence.restored,
            history_capacity=s.acquisition.ring_capacity,
        )
        worker = self.worker or IdentificationWorker(
            ModelRef.from_settings(s), timeout_s=s.identification.timeout_s
        )
        self.service = SoftSensorService(
            core,
            worker=worker,
            writer=self.persistence.sink,
            session_factory=self.persistence.session_factory,
            db_reads=self.persistence.reads,
            sources={"modbus": daq, "can": can},
            clock=self.clock,
            on_event=self.on_event,
            growth=growth_server(model, s, self.persistence.restored, context=self.growth_context),
            **engine_parts(s, loop_lag=self.loop_lag),
        )
        self.persistence.on_open = self.service.ids_known  # a database answering late: small ids
        await self.service.start()
        self.devices = (daq, can)
        if acquire:
            self._start_acquisition()
        for name in enabled_outlets(s, api=api, registry=self.outlets or OUTLETS):
            await self._start_outlet(name)

    def start_acquisition(self) -> None:
        """Start polling the devices given to ``start()`` (once)."""
        with spindle_context(self.settings.spindle.id):
            self._start_acquisition()

    def _start_acquisition(self) -> None:
        s = self.settings
        assert self.devices is not None and self.ring is not None and self.service is not None, "start first"
        if self.acquisition_task is not None:
            return
        daq, can = self.devices
        self.acquisition = Acquisition(
            daq,
            can,
            self.ring,
            period_s=s.acquisition.sample_period_s / self.speedup,
            on_sample=self.service.on_sample,
            now=self.sample_clock or self.clock,
        )
        poll = min(s.modbus.poll_interval_s, s.acquisition.sample_period_s / 2.0) / self.speedup
        self.acquisition_task = asyncio.ensure_future(self.acquisition.run(poll_interval_s=poll))

    async def start_outlet(self, name: str) -> Outlet:
        """Build, start and subscribe the outlet ``name`` (``OutletError`` if it cannot be loaded)."""
        with spindle_context(self.settings.spindle.id):
            return await self._start_outlet(name)

    async def _start_outlet(self, name: str) -> Outlet:
        assert self.service is not None, "start first"
        factory = (self.outlets or {}).get(name) or load_factory(name)
        ctx = OutletContext(
            settings=self.settings,
            service=self.service,
            clock=self.clock,
            simulated=self.simulated_time,
            speedup=self.clock.speedup,
            on_event=self.on_event,
        )
        outlet = factory(ctx)
        await outlet.start()
        self.running_outlets[name] = outlet
        self.service.subscribe(outlet)
        return outlet

    @property
    def api_server(self) -> uvicorn.Server | None:
        """The REST outlet's uvicorn server (None: no API)."""
        return getattr(self.running_outlets.get("rest"), "server", None)

    @property
    def api_task(self) -> asyncio.Task[None] | None:
        return getattr(self.running_outlets.get("rest"), "task", None)

    async def wait_api(self, timeout_s: float = 20.0) -> None:
        """Wait until the API server accepts connections (raises TimeoutError)."""
        deadline = time.monotonic() + timeout_s
        while self.api_server is None or not self.api_server.started:
            task = self.api_task
            if task is None or (task.done() and (task.cancelled() or task.exception() is not None)):
                raise RuntimeError(
                    f"API server did not start: {task and not task.cancelled() and task.exception()}"
                )
            if time.monotonic() > deadline:
                raise TimeoutError(f"API server not up within {timeout_s:.0f} s")
            await asyncio.sleep(0.05)

    @property
    def url(self) -> str:
        return f"http://{self.settings.api.host}:{self.settings.api.port}/"

    async def stop(self) -> None:
        """Stop the outlets (the API gracefully), the acquisition, the worker and the writer (flushing it)."""
        with spindle_context(self.settings.spindle.id):
            await self._stop()

    async def _stop(self) -> None:
        for name, outlet in reversed(list(self.running_outlets.items())):
            if self.service is not None:
                self.service.unsubscribe(outlet)
            try:
                await outlet.close()
            except Exception as err:  # stop the rest regardless
                self.on_event(f"shutdown: outlet {name} failed to close: {type(err).__name__}: {err}")
        self.running_outlets.clear()
        task = self.acquisition_task
        if task is not None:
            task.cancel()
            # asyncio.wait, not wait_for: on a timeout wait_for cancels and then waits for the task
            # without limit, which hung the shutdown when a client library swallowed the cancellation.
            done, _ = await asyncio.wait({task}, timeout=10.0)
            if not done:
                self.on_event(f"shutdown: {task.get_name()} did not stop within 10 s; abandoned")
            elif not task.cancelled():
                task.exception()  # retrieved: a failure at shutdown was already reported by the task
        if self.devices is not None:
            for src in self.devices:
                with contextlib.suppress(Exception):
                    await src.close()
        if self.service is not None:
            await self.service.close()
        if self.persistence is not None:
            await asyncio.to_thread(self.persistence.close)
