"""``chtc demo``: the whole soft sensor against simulated devices driven by the virtual plant, on SQLite.

The virtual plant (``model.plant.VirtualPlant``, its own finer mesh and ground truth) runs a seeded machining
duty cycle until the demo is stopped (``simulator.endless``: ``--idle-min`` at rest, then the speed changes
every 1–6 min over 0–7000 rpm with torque; computed 30 plant minutes ahead, chunk by chunk). The plant and
the simulated Modbus DAQ and CAN node that serve it at ``--speedup`` plant seconds per wall second run in a
child process (``simulator.rigproc``: a busy service cannot starve them, and they take nothing from the
service's GIL), on free loopback ports: Modbus TCP, and CAN through a python-can-remote hub, as ``chtc
simulate`` serves them. The unchanged service (real drivers, ring buffer, detector, scheduler, worker
process, database writer, the core in its own thread) and the API with the dashboard run in this process.
Progress lines report detected conditions and identifications (H with fit, and the plant's true H for
comparison).

All timestamps are simulated plant time (UTC): they start at the real time (on a ``--database-url`` an
earlier demo left, a minute after the newest time it holds: ``clock_start_after``) and run ``--speedup``
times faster; ``/healthz`` says so (``clock.simulated``) and the dashboard marks its times "plant time".
The demo writes with a token: ``api.token`` from ``--config``, else one generated for this run and printed,
with the dashboard URL carrying it in its fragment (``#write-token=...``: a fragment is never sent to the
server, so it lands in no request log). Stops on Ctrl-C or after ``--duration`` wall seconds.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import logging
import secrets
import signal
import tempfile
import time
from collections.abc import Callable
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from service.commands._common import (
    check_database_url,
    check_listens,
    override,
    port_number,
    positive_float,
)
from service.contracts.snapshots import IdentificationRecord
from service.core.jobbook import MAP_METHOD
from service.logctx import install_logging, set_default
from service.shell.heap import freeze_startup_heap

if TYPE_CHECKING:
    from service.contracts.snapshots import IdentificationRecord
    from service.host.runtime import Runtime
    from service.settings import Settings
    from simulator.endless import PlantRows
    from simulator.rigproc import RigProcess


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
    parser.add_argument("--seed", type=int, default=0, help="duty-cycle, plant noise and identification seed")
    parser.add_argument(
        "--idle-min",
        type=float,
        default=None,
        help="plant minutes at rest before the machining starts (default: the offset baseline's equilibrium "
        "window identification.offset_rest_s plus 5 min, 10 min with the defaults; shorter: the demo runs "
        "without an offset baseline and its growth's CI is wider)",
    )
    parser.add_argument(
        "--segment-min",
        type=positive_float,
        default=None,
        help="plant minutes per speed (default: 1-6 min at random, as on a machining centre)",
    )
    parser.add_argument("--quiet", action="store_true", help="only print the URL and errors")


def demo_settings(args: argparse.Namespace, db_url: str) -> tuple[Settings, str | None]:
    """Settings from ``--config`` with the demo's API address, database and seed, validated
    (``SettingsError`` / ``CommandError`` naming the key), and the write token generated for this run (None
    when ``api.token`` is configured: it is then used, and never printed)."""
    from service.settings import load_settings

    s = load_settings(args.config)
    generated = None
    if s.api.token is None:
        generated = secrets.token_urlsafe(24)
        s = override(s, "api", token=generated)
    port = args.port
    if port == 0:
        from service.host.runtime import free_port

        port = free_port(args.host)
    s = override(s, "api", host=args.host, port=port)
    s = override(s, "database", url=db_url)
    # the virtual plant starts at rest in equilibrium: the demo's controller is zeroed there (a real
    # installation sets its zero at commissioning: docs/commissioning.md)
    # the demo's plant has the spindle description's own mechanics: nothing to commission; and sensors
    # without offsets (model.plant.VirtualPlant's default): usable before a baseline (its first rest takes
    # one: idle_minutes)
    s = override(
        s,
        "compensation",
        reference_on_first_start=True,
        require_mechanics_calibration=False,
        require_offset_baseline=False,
    )
    return override(s, "experimental", seed=args.seed), generated


class Printer:
    """Progress lines stamped with the plant time and, for identifications, the plant's true H.

    The truth is the plant's H at the middle of the identified window (``current()``, the record just
    stored), not at the moment the line is printed: by then the plant may run at the next speed. A speed-map
    fit's record (method ``speed-map``) holds the map's H at its launch condition, the window's end (its
    window spans several speeds): its truth is the plant's there.
    ``rows()`` is the plant's rows so far (``times_s``, ``speed_rpm``, ``h_true``; they grow as the plant
    runs); ``clock`` is the service's (simulated UTC) clock; ``rig.plant_time_s()`` the plant time now.
    """

    def __init__(
        self,
        rows: Callable[[], PlantRows | None],
        *,
        quiet: bool,
        clock: Callable[[], datetime] | None = None,
        current: Callable[[], IdentificationRecord | None] | None = None,
    ) -> None:
        self.rows, self.quiet = rows, quiet
        self.clock, self.current = clock, current
        self.rig: RigProcess | None = None

    def __call__(self, msg: str) -> None:
        if self.quiet:
            return
        elapsed = self.rig.plant_time_s() if self.rig is not None else 0.0
        h, rem = divmod(int(elapsed), 3600)
        line = f"[plant +{h:02d}:{rem // 60:02d}:{rem % 60:02d}] {msg}"
        rows = self.rows()
        if rows is not None and msg.startswith(("identification", "map identification")) and " ok:" in msg:
            rec = self.current() if self.current is not None else None
            if msg.startswith("map") and rec is not None:  # its line has no H: the map's at the launch
                served = ", ".join(f"{x:.1f}" for x in rec.h)
                line += f"\n{' ' * 17}map H = [{served}] at {rec.condition.speed_rpm:.0f} rpm"
            k, where = self._truth_row(rows, elapsed)
            truth = ", ".join(f"{x:.1f}" for x in rows.h_true[k])
            line += f"\n{' ' * 17}plant truth H = [{truth}] ({where})"
        print(line, flush=True)

    def _truth_row(self, rows: PlantRows, elapsed: float) -> tuple[int, str]:
        """The plant row at the identified window's middle, and how it was chosen."""
        t_plant, where = elapsed, "now"
        rec = self.current() if self.current is not None else None
        if rec is not None and self.clock is not None:
            at_end = getattr(rec, "method", None) == MAP_METHOD
            at = rec.window_to if at_end else rec.window_from + (rec.window_to - rec.window_from) / 2
            t_plant = elapsed - (self.clock() - at).total_seconds()
            if at_end:  # the map's H at the speed its line names: the plant there, from the window's end on
                k0 = _row(rows, t_plant)
                k = _row_at_speed(rows, k0, float(rec.condition.speed_rpm))
                if k is not None and k != k0:
                    return k, f"the map at {float(rows.speed_rpm[k]):.0f} rpm, next to the window's end"
            label = "the map at the window's end" if at_end else "mid-window"
            where = f"{label}, {float(rows.speed_rpm[_row(rows, t_plant)]):.0f} rpm"
        return _row(rows, t_plant), where


def _row_at_speed(rows: PlantRows, k0: int, speed_rpm: float) -> int | None:
    """The first row from ``k0`` on at ``speed_rpm`` (±1 rpm), else the last one before it (None: none)."""
    at = np.flatnonzero(np.abs(np.asarray(rows.speed_rpm, dtype=float) - speed_rpm) <= 1.0)
    if at.size == 0:
        return None
    later = at[at >= k0]
    return int(later[0]) if later.size else int(at[-1])


def _row(rows: PlantRows, t_plant: float) -> int:
    return min(int(np.searchsorted(rows.times_s, t_plant)), len(rows.times_s) - 1)


# the rest beyond the baseline's equilibrium window: the first samples, the filter's start
IDLE_MARGIN_S = 300.0


def idle_minutes(args: argparse.Namespace, settings: Settings) -> float:
    """The plant's rest before the machining [min]: ``--idle-min``, else long enough for the offset baseline
    (``identification.offset_rest_s`` of idle samples at equilibrium, plus ``IDLE_MARGIN_S``). The endless
    duty cycle never rests that long again, so a demo whose first rest is shorter runs without a baseline:
    every channel's offset stays unknown (1σ ``identification.offset_sd_c``, 0.17 °C), the filter widens its
    measurement noise by it and the growth's 95 % CI half-width sits at the 2 µm tolerance (issue 42)."""
    if args.idle_min is not None:
        return float(args.idle_min)
    return (settings.identification.offset_rest_s + IDLE_MARGIN_S) / 60.0


def dashboard_url(base: str, token: str | None) -> str:
    """The dashboard's URL; with a generated write token in its fragment (``#write-token=...``), which the
    browser never sends to the server: the page keeps it in the tab's sessionStorage for its write buttons."""
    return base if token is None else f"{base}#write-token={token}"


async def run_demo(args: argparse.Namespace, settings: Settings, token: str | None = None) -> int:
    from service.host.runtime import Runtime, ScaledClock
    from simulator.rigproc import RigPlan, RigProcess
    from simulator.simrig import make_drivers

    db_url = settings.database.url
    clock = ScaledClock(args.speedup)
    idle_min = idle_minutes(args, settings)
    resume_at = await asyncio.to_thread(clock_start_after, db_url)
    if resume_at is not None:
        clock.start(at=resume_at)
        at = resume_at.isoformat(timespec="seconds")
        print(f"plant clock starts at {at}, after what the database holds", flush=True)
    # the devices and the plant run in a process of their own, as real ones do: it computes the plant's
    # first chunk while this one loads the model
    plan = RigPlan.on_free_ports(
        spindle=settings.model.spindle,
        seed=args.seed,
        idle_s=60.0 * idle_min,
        segment_s=None if args.segment_min is None else 60.0 * args.segment_min,
        speedup=args.speedup,
    )
    rig = RigProcess(plan)
    runtime = Runtime(settings=settings, clock=clock, on_event=lambda m: None, simulated_time=True)
    stop = asyncio.Event()
    _install_signals(stop)
    try:
        print(
            "loading the model (the first run builds the reduced model: 1-4 min by the machine's load; "
            "later runs load it from the cache) ...",
            flush=True,
        )
        await asyncio.to_thread(runtime.load)
        print("starting the virtual plant's machining cycle ...", flush=True)
        await rig.computed()
        printer = Printer(lambda: rig.rows, quiet=args.quiet, clock=clock, current=lambda: _current(runtime))
        runtime.on_event = printer
        printer.rig = rig
        daq, can_sensor = make_drivers(settings, plan.address(), clock=clock)
        # the simulated devices listen before the drivers first poll them (no "cannot connect" warning)
        await runtime.start(daq=daq, can=can_sensor, api=True, acquire=False)
        await runtime.wait_api()
        await rig.start()
        runtime.start_acquisition()
        freeze_startup_heap()  # as chtc run: no full collector pass over the start-up's objects
        _announce(args, runtime.url, db_url, token, idle_min)
        started = time.monotonic()
        while not stop.is_set():
            if args.duration is not None and time.monotonic() - started >= args.duration:
                break
            rig.check()  # a failure of the plant or the devices is the demo's
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(stop.wait(), timeout=0.2)
    finally:
        await runtime.stop()
        await rig.stop()
    print("demo stopped", flush=True)
    return 0


def clock_start_after(db_url: str, *, now: datetime | None = None) -> datetime | None:
    """Where the plant clock starts on a database an earlier demo left: a minute after the newest time it
    holds, when that is later than now (its accelerated clock ran ahead of the wall clock); None: now. A
    clock started behind the stored times would date the new samples before the stored live state,
    conditions and identifications (issue 41)."""
    from service.store.engine import create_db_engine
    from service.store.newest import newest_time

    try:
        engine = create_db_engine(db_url, create_dirs=False)
    except Exception:  # an unusable URL is the runtime's to report, with its checks
        return None
    try:
        newest = newest_time(engine)
    except Exception:  # an unreadable database is the runtime's to report, with its checks
        return None
    finally:
        engine.dispose()
    now = now if now is not None else datetime.now(UTC)
    if newest is None or newest < now:
        return None
    return newest + timedelta(minutes=1)


def _announce(
    args: argparse.Namespace, base_url: str, db_url: str, token: str | None, idle_min: float
) -> None:
    print(f"dashboard: {dashboard_url(base_url, token)}", flush=True)
    print(f"API: {base_url}api/v1/compensation; database: {_safe(db_url)}", flush=True)
    if token is not None:
        print(
            f"write token (this run only; the dashboard URL carries it): {token}\n"
            f"  e.g. curl -X POST -H 'Authorization: Bearer {token}' {base_url}api/v1/identifications",
            flush=True,
        )
    else:
        print("write token: the configured api.token", flush=True)
    every = "1-6 min" if args.segment_min is None else f"{args.segment_min:g} min"
    print(
        f"plant profile: {idle_min:g} min at rest, then a machining cycle (a new speed every "
        f"{every}, 0-7000 rpm) until stopped; plant time runs x{args.speedup:g} (1 wall s = "
        f"{args.speedup:g} plant s) and every time shown is plant time; Ctrl-C stops",
        flush=True,
    )


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
    """The log format with the spindle id (``service.logctx``; the id is set once the settings are read,
    ``log_spindle_default``); pymodbus logs every timeout and dumps frames; the drivers count and report
    those errors already."""
    install_logging(default=None)
    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)


def log_spindle_default(settings: Settings) -> None:
    """Log lines outside every spindle's context name this instance's spindle (none when it hosts several:
    ``-``, never a wrong id)."""
    set_default(None if settings.spindles else settings.spindle.id)


def main(args: argparse.Namespace) -> int:
    """Settings and the API port are checked before anything slow starts; a problem is one line (exit 2)."""
    quiet_third_party_logs()
    with tempfile.TemporaryDirectory(prefix="chtc-demo-") as tmp:
        db_url = args.database_url or f"sqlite:///{Path(tmp) / 'demo.db'}"
        settings, token = demo_settings(args, db_url)
        log_spindle_default(settings)
        if args.database_url is not None:
            check_database_url(settings.database.url, "--database-url")
        check_listens(settings)
        from service.serve.opcua.preflight import check_opcua_files

        if settings.opcua.enabled:  # an unreadable certificate: one line before the model loads
            check_opcua_files(settings.opcua)
        return asyncio.run(run_demo(args, settings, token))
