"""``chtc demo``: the whole soft sensor against simulated devices driven by the virtual plant, on SQLite.

The virtual plant (``model.plant.VirtualPlant``, its own finer mesh and ground truth) runs an operating
profile with several speed changes (3000 → 4000 → 5000 → 4000 → 3000 rpm, ``--segment-min`` each); the
simulated Modbus DAQ and CAN node serve it on a free loopback port and a private virtual CAN channel at
``--speedup`` plant seconds per wall second. The unchanged service (real drivers, ring buffer, detector,
scheduler, worker process, database writer) and the API with the dashboard run in this process. Progress
lines report detected conditions and identifications (H with fit, and the plant's true H for comparison).

All timestamps are simulated UTC: they start at the real time and run ``--speedup`` times faster. After the
profile ends the plant holds its last state. Stops on Ctrl-C or after ``--duration`` wall seconds.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import logging
import signal
import tempfile
import time
from collections.abc import Callable
from datetime import datetime
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from service.commands._common import (
    check_database_url,
    check_listen,
    override,
    port_number,
    positive_float,
)
from service.engine.jobbook import MAP_METHOD

if TYPE_CHECKING:
    from model.plant import PlantRun, Segment
    from service.engine.runtime import Runtime
    from service.serve.interface import IdentificationRecord
    from service.settings import Settings
    from service.sim.simrig import SimRig

SPEEDS_RPM = (3000.0, 4000.0, 5000.0, 4000.0, 3000.0)
AMBIENT_C = (23.2, 21.8, 22.0, 22.5, 23.0)
TORQUE_NM = (5.0, 6.0, 8.0, 6.0, 5.0)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--config", type=Path, default=None, help="settings TOML (default: built-in defaults)"
    )
    parser.add_argument("--host", default="127.0.0.1", help="API/dashboard host")
    parser.add_argument(
        "--port", type=port_number, default=8000, help="API/dashboard port; 0 picks a free one"
    )
    parser.add_argument(
        "--speedup",
        type=positive_float,
        default=60.0,
        help="plant seconds per wall second (60: 1 h/min)",
    )
    parser.add_argument(
        "--database-url", default=None, help="SQLAlchemy URL (default: a fresh SQLite file in a temp dir)"
    )
    parser.add_argument(
        "--duration", type=float, default=None, help="stop after this many wall seconds (default: Ctrl-C)"
    )
    parser.add_argument("--seed", type=int, default=0, help="plant noise seed and identification seed")
    parser.add_argument("--segment-min", type=positive_float, default=60.0, help="plant minutes per speed")
    parser.add_argument("--quiet", action="store_true", help="only print the URL and errors")


def build_profile(segment_min: float, *, idle_min: float = 5.0) -> list[Segment]:
    """The demo's operating profile as ``model.plant.Segment`` (s, rpm, N·m, °C).

    It starts with the spindle idle (cold, uniform at ambient) for ``idle_min``: the service sees the machine
    start from a known state, as in the paper's runs.
    """
    from model.plant import Segment

    idle = [Segment(60.0 * idle_min, 0.0, 0.0, AMBIENT_C[0])] if idle_min > 0 else []
    return idle + [
        Segment(60.0 * segment_min, n, m, a) for n, m, a in zip(SPEEDS_RPM, TORQUE_NM, AMBIENT_C, strict=True)
    ]


def demo_settings(args: argparse.Namespace, db_url: str) -> Settings:
    """Settings from ``--config`` with the demo's API address, database and seed, validated
    (``SettingsError`` / ``CommandError`` naming the key)."""
    from service.settings import load_settings

    s = load_settings(args.config)
    port = args.port
    if port == 0:
        from service.engine.runtime import free_port

        port = free_port(args.host)
    s = override(s, "api", host=args.host, port=port)
    s = override(s, "database", url=db_url)
    # the virtual plant starts at rest in equilibrium: the demo's controller is zeroed there (a real
    # installation sets its zero at commissioning: docs/commissioning.md)
    s = override(s, "compensation", reference_on_first_start=True)
    return override(s, "experimental", seed=args.seed)


class Printer:
    """Progress lines stamped with the plant time and, for identifications, the plant's true H.

    The truth is the plant's H at the middle of the identified window (``current()``, the record just
    stored), not at the moment the line is printed: by then the plant may run at the next speed. A speed-map
    fit's record (method ``speed-map``) holds the map's H at its launch condition, the window's end (its
    window spans several speeds): its truth is the plant's there.
    ``clock`` is the service's (simulated UTC) clock; ``rig.plant_time_s()`` the plant time now.
    """

    def __init__(
        self,
        run: PlantRun,
        *,
        quiet: bool,
        clock: Callable[[], datetime] | None = None,
        current: Callable[[], IdentificationRecord | None] | None = None,
    ) -> None:
        self.run, self.quiet = run, quiet
        self.clock, self.current = clock, current
        self.rig: SimRig | None = None

    def __call__(self, msg: str) -> None:
        if self.quiet:
            return
        elapsed = self.rig.plant_time_s() if self.rig is not None else 0.0
        h, rem = divmod(int(elapsed), 3600)
        line = f"[plant +{h:02d}:{rem // 60:02d}:{rem % 60:02d}] {msg}"
        if msg.startswith(("identification", "map identification")) and " ok:" in msg:
            rec = self.current() if self.current is not None else None
            if msg.startswith("map") and rec is not None:  # its line has no H: the map's at the launch
                served = ", ".join(f"{x:.1f}" for x in rec.h)
                line += f"\n{' ' * 17}map H = [{served}] at {rec.condition.speed_rpm:.0f} rpm"
            k, where = self._truth_row(elapsed)
            truth = ", ".join(f"{x:.1f}" for x in self.run.h_true[k])
            line += f"\n{' ' * 17}plant truth H = [{truth}] ({where})"
        print(line, flush=True)

    def _truth_row(self, elapsed: float) -> tuple[int, str]:
        """The plant row at the identified window's middle, and how it was chosen."""
        t_plant, where = elapsed, "now"
        rec = self.current() if self.current is not None else None
        if rec is not None and self.clock is not None:
            at_end = getattr(rec, "method", None) == MAP_METHOD
            at = rec.window_to if at_end else rec.window_from + (rec.window_to - rec.window_from) / 2
            t_plant = elapsed - (self.clock() - at).total_seconds()
            label = "the map at the window's end" if at_end else "mid-window"
            where = f"{label}, {float(self.run.speed_rpm[self._row(t_plant)]):.0f} rpm"
        return self._row(t_plant), where

    def _row(self, t_plant: float) -> int:
        return min(int(np.searchsorted(self.run.times_s, t_plant)), len(self.run.times_s) - 1)


async def run_demo(args: argparse.Namespace, settings: Settings) -> int:
    from model.geometry import load_spindle
    from model.plant import VirtualPlant
    from service.engine.runtime import Runtime, ScaledClock
    from service.sim.simrig import SimAddress, make_drivers, plant_rig

    db_url = settings.database.url
    clock = ScaledClock(args.speedup)
    print("loading the model (the first run builds the reduced model, about a minute) ...", flush=True)
    runtime = Runtime(settings=settings, clock=clock, on_event=lambda m: None)
    await asyncio.to_thread(runtime.load)
    print("running the virtual plant over the demo profile ...", flush=True)
    plant = VirtualPlant(load_spindle(settings.model.spindle), seed=args.seed)
    run = await asyncio.to_thread(plant.run, build_profile(args.segment_min), dt_s=10.0)
    printer = Printer(run, quiet=args.quiet, clock=clock, current=lambda: _current(runtime))
    runtime.on_event = printer
    address = SimAddress.free(speedup=args.speedup)
    daq, can_sensor = make_drivers(settings, address, clock=clock)
    stop = asyncio.Event()
    _install_signals(stop)
    rig = None
    try:
        # the simulated devices listen before the drivers first poll them (no "cannot connect" warning)
        await runtime.start(daq=daq, can=can_sensor, api=True, acquire=False)
        await runtime.wait_api()
        rig = printer.rig = await plant_rig(run, address=address)
        runtime.start_acquisition()
        print(
            f"dashboard: {runtime.url}   (API: {runtime.url}api/v1/chtc; database: {_safe(db_url)})",
            flush=True,
        )
        print(
            f"plant profile: idle, then {' -> '.join(f'{n:.0f}' for n in SPEEDS_RPM)} rpm, "
            f"{args.segment_min:.0f} min each, "
            f"x{args.speedup:g} ({args.segment_min * 60 / args.speedup:.0f} s per segment); Ctrl-C stops",
            flush=True,
        )
        started = time.monotonic()
        while not stop.is_set():
            if args.duration is not None and time.monotonic() - started >= args.duration:
                break
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(stop.wait(), timeout=0.2)
    finally:
        await runtime.stop()
        if rig is not None:
            await rig.stop()
    print("demo stopped", flush=True)
    return 0


def _current(runtime: Runtime) -> IdentificationRecord | None:
    """The identification record the core stored last (None before the first)."""
    service = runtime.service
    return None if service is None else service.view.current


def _install_signals(stop: asyncio.Event) -> None:
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        with contextlib.suppress(NotImplementedError, RuntimeError):
            loop.add_signal_handler(sig, stop.set)


def _safe(url: str) -> str:
    from sqlalchemy.engine import make_url

    return make_url(url).render_as_string(hide_password=True)


def quiet_third_party_logs() -> None:
    """pymodbus logs every timeout and dumps frames; the drivers count and report those errors already."""
    logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)


def main(args: argparse.Namespace) -> int:
    """Settings and the API port are checked before anything slow starts; a problem is one line (exit 2)."""
    quiet_third_party_logs()
    with tempfile.TemporaryDirectory(prefix="chtc-demo-") as tmp:
        db_url = args.database_url or f"sqlite:///{Path(tmp) / 'demo.db'}"
        settings = demo_settings(args, db_url)
        if args.database_url is not None:
            check_database_url(settings.database.url, "--database-url")
        check_listen(settings.api.host, settings.api.port)
        return asyncio.run(run_demo(args, settings))
