"""``chtc replay``: recorded logs -> simulated devices -> the unchanged service; every identification saved.

The simulated Modbus DAQ serves the temperature CSV and the CAN log is replayed on a private virtual CAN
channel (``drivers.sim.replay``), at ``--speedup`` recorded seconds per wall second. The service runs exactly
as in production (drivers, ring buffer, detector, scheduler, worker process, database writer); its clock
reads the recorded time, so stored timestamps are the log's. When the log ends (plus the time for running
identifications) every identification is in the database and in ``--out`` (JSON, or CSV by suffix).
Each identification is printed as ``chtc identify`` prints it (``format_record``: its status, speed-map or
per-condition fit, H1-H7 with 95 % CIs and ``?`` marks), and a summary line at the end.

The DAQ serves the recording reduced to the rows the acquisition samples (``write_acquisition_csv``: one row
per ``acquisition.sample_period_s``, the newest recorded row at each sample instant), and the acquisition is
started in phase with them, so a replay sees the same samples as ``chtc identify`` on the same files, also for
real-time recordings with one jittered row per second; see docs/design/service.md for what can still differ.

The growth history (docs/design/growth.md): while the log plays, what ``/compensation`` serves is read every
``--growth-every-s`` recorded seconds and at each new identification (``GrowthLog``), and written to
``--growth-out`` if given (JSON, or CSV by suffix; nothing is written without it): the time (UTC), the
status and usability of ``/compensation`` (the policy's verdict on the growth), the identification, the
axial and radial growth in µm with their 95 % CIs and 0.1-µm integers, and the steady axial growth. Each
identification in ``--out`` (JSON) carries ``growth``: the first served after it became current (null if it
did not succeed), as ``chtc identify --json`` does.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import csv
import json
import signal
import sys
import tempfile
import time
from collections.abc import Callable
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import TYPE_CHECKING

from service.contracts.errors import NotReadyError
from service.contracts.snapshots import CompensationSnapshot, IdentificationRecord

if TYPE_CHECKING:
    from drivers.sim.replay import Replay
    from service.contracts.snapshots import CompensationSnapshot, IdentificationRecord
    from service.host.runtime import ScaledClock
    from service.settings import Settings
    from service.shell.service import SoftSensorService

from drivers.logsamples import REPLAY_PHASE, write_acquisition_csv
from service.commands._common import (
    CommandError,
    check_database_url,
    check_listen,
    check_log_arguments,
    override,
    port_number,
    positive_float,
)
from service.commands.identify import format_record, growth_dict, num, record_dict, summary_line
from service.errors import ServiceError


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("csv", type=Path, help="temperature CSV (chtc record / drivers.logs format)")
    parser.add_argument(
        "can", type=Path, nargs="?", default=None, help="CAN log (.blf/.asc/.log/.csv/.trc/.mf4)"
    )
    parser.add_argument(
        "--config", type=Path, default=None, help="settings TOML (default: built-in defaults)"
    )
    parser.add_argument(
        "--speedup", type=positive_float, default=60.0, help="recorded seconds per wall second"
    )
    parser.add_argument(
        "--database-url", default=None, help="SQLAlchemy URL (default: database.url of the settings)"
    )
    parser.add_argument("--out", type=Path, default=Path("identifications.json"), help=".json or .csv output")
    parser.add_argument("--api", action="store_true", help="also serve the API/dashboard (on --host:--port)")
    parser.add_argument("--host", default=None, help="with --api: API host (default: api.host, 127.0.0.1)")
    parser.add_argument(
        "--port", type=port_number, default=None, help="with --api: API port (default: api.port, 8000)"
    )
    parser.add_argument(
        "--grace", type=float, default=30.0, help="wall s to wait for running identifications"
    )
    parser.add_argument(
        "--growth-out",
        type=Path,
        default=None,
        help="write the growth history to this .json or .csv (default: not written)",
    )
    parser.add_argument(
        "--growth-every-s",
        type=positive_float,
        default=60.0,
        help="recorded seconds between growth history rows (default 60; and at each identification)",
    )


class GrowthLog:
    """The growth as ``/compensation`` served it during a replay: ``rows`` (time order) and, per
    identification id, the first row served after it became current (``by_id``)."""

    def __init__(self) -> None:
        self.rows: list[dict[str, object]] = []
        self.by_id: dict[int, dict[str, object]] = {}

    def add(self, snap: CompensationSnapshot) -> None:
        g = growth_dict(snap.growth)
        assert g is not None
        row: dict[str, object] = {
            "at": g.pop("at"),
            "status": str(snap.status),
            "usable_for_compensation": bool(snap.usable_for_compensation),
            "reason": snap.reason,
            "identification_id": snap.identification_id,
            "unit": "µm",
        } | g
        if self.rows and self.rows[-1]["at"] == row["at"]:
            return
        self.rows.append(row)
        if snap.identification_id is not None:  # the first growth served with each identification's H
            self.by_id.setdefault(snap.identification_id, row)

    def write(self, path: Path) -> None:
        if path.suffix.lower() == ".csv":
            with path.open("w", newline="", encoding="utf-8") as f:
                w = csv.writer(f)
                parts = ("axial", "radial", "steady_axial")
                w.writerow(
                    ["at", "status", "usable_for_compensation", "identification_id", "t_ref_c"]
                    + [f"{p}_{k}" for p in parts for k in ("um", "ci95_lo_um", "ci95_hi_um", "0p1um")]
                )
                for r in self.rows:
                    vals: list[object] = []
                    for p in parts:
                        v = r[p]
                        assert isinstance(v, dict)
                        vals += [v["um"], v["ci95_um"][0], v["ci95_um"][1], v["plc_0p1um"]]
                    head = [r[k] for k in ("at", "status", "usable_for_compensation", "identification_id")]
                    w.writerow([*head, r["t_ref_c"], *vals])
        else:
            path.write_text(json.dumps(self.rows, indent=2) + "\n", encoding="utf-8")


async def watch_growth(
    service: SoftSensorService, log: GrowthLog, *, every_s: float, poll_wall_s: float
) -> None:
    """Read ``/compensation`` (off the loop) every ``every_s`` of the live state's time and at each new
    identification, until cancelled; stops if the service has no growth model."""

    last_t: float | None = None
    while True:
        v = service.view
        live, rec = v.live, v.current
        if live is not None and rec is not None and not v.current_from_restore:
            due = last_t is None or live.t - last_t >= every_s - 1e-6 or rec.id not in log.by_id
            if due:
                try:
                    snap = await asyncio.to_thread(service.compensation)
                except NotReadyError:
                    return
                if snap is not None:
                    log.add(snap)
                    last_t = snap.growth.at.timestamp()
        await asyncio.sleep(poll_wall_s)


def write_out(path: Path, records: list[IdentificationRecord], growth: GrowthLog | None = None) -> None:
    if path.suffix.lower() == ".csv":
        with path.open("w", newline="", encoding="utf-8") as f:
            w = csv.writer(f)
            w.writerow(
                ["id", "outcome", "condition_id", "speed_rpm", "ambient_c", "window_from", "window_to"]
                + [f"h{i}_w_m2k" for i in range(1, 8)]
                + [f"h{i}_ci95_lo" for i in range(1, 8)]
                + [f"h{i}_ci95_hi" for i in range(1, 8)]
                + ["fit", "rmse_c", "message"]
            )
            for r in records:
                c = r.condition
                head = [r.id, r.outcome, c.id, num(c.speed_rpm), num(c.ambient_c), r.window_from.isoformat()]
                zones = [num(x) for x in (*r.h, *r.ci95_lo, *r.ci95_hi)]
                w.writerow([*head, r.window_to.isoformat(), *zones, num(r.fit), num(r.rmse_c), r.message])
    else:
        by_id = growth.by_id if growth is not None else {}
        rows = [record_dict(r) | {"growth": by_id.get(r.id) if r.outcome == "ok" else None} for r in records]
        path.write_text(json.dumps(rows, indent=2) + "\n", encoding="utf-8")


async def run_replay(
    args: argparse.Namespace, settings: Settings, *, growth: GrowthLog | None = None
) -> list[IdentificationRecord]:
    """Replay the logs; every identification, oldest first. ``growth``: filled with the growth history
    (``args.growth_every_s``, default 60 s)."""
    with tempfile.TemporaryDirectory(prefix="chtc-replay-") as tmp:
        served = Path(tmp) / "acquired.csv"
        period_s = settings.acquisition.sample_period_s
        await asyncio.to_thread(write_acquisition_csv, args.csv, args.can, served, period_s=period_s)
        return await _replay(args, settings, served, growth)


async def _replay(
    args: argparse.Namespace, settings: Settings, served_csv: Path, growth: GrowthLog | None
) -> list[IdentificationRecord]:
    from service.host.runtime import Runtime, ScaledClock
    from simulator.simrig import SimAddress, make_drivers, replay_rig

    stop = asyncio.Event()  # SIGINT or SIGTERM: stop, store what was identified so far (issue 41)
    install_stop_signals(stop)
    clock = ScaledClock(args.speedup)
    period_s = settings.acquisition.sample_period_s
    lines = RecordLines()
    runtime = Runtime(settings=settings, clock=clock, on_event=lines.event, simulated_time=True)
    model = await asyncio.to_thread(runtime.load)
    lines.box = model.ref.h_box  # the CIs as chtc identify prints them (issue 41)
    address = SimAddress.free(speedup=args.speedup)
    rig = await replay_rig(served_csv, args.can, address=address, begin=False)
    replay = rig.replay
    assert replay is not None  # a replay rig
    origin = datetime.fromtimestamp(replay.t_ref + REPLAY_PHASE * period_s, tz=UTC)
    runtime.sample_clock = GridClock(clock, origin=origin, period_s=period_s)
    daq, can_sensor = make_drivers(settings, address, clock=clock)
    watcher: asyncio.Task[None] | None = None
    try:
        await runtime.start(daq=daq, can=can_sensor, api=args.api)
        lines.follow(runtime.service)
        if growth is not None and runtime.service is not None:
            every_s = float(getattr(args, "growth_every_s", 60.0))
            poll = 0.25 * period_s / args.speedup
            watch = watch_growth(runtime.service, growth, every_s=every_s, poll_wall_s=poll)
            watcher = asyncio.create_task(watch)
        if args.api:
            await runtime.wait_api()
            print(f"dashboard: {runtime.url}   (API: {runtime.url}api/v1/chtc)", flush=True)
        if not stop.is_set():
            await _begin_in_phase(replay, clock, settings.acquisition.sample_period_s / args.speedup)
        tail_s = 2.0 * settings.acquisition.sample_period_s / args.speedup
        await _sleep_unless(stop, replay.duration_s + tail_s)
        deadline = time.monotonic() + args.grace
        service = runtime.service
        assert service is not None
        while service.view.running_job is not None and time.monotonic() < deadline and not stop.is_set():
            await _sleep_unless(stop, 0.1)
        records = list(reversed(service.view.records))
        lines.print_new()
        if watcher is not None and not stop.is_set():  # the growth served after the last identification
            await _sleep_unless(stop, 2.0 * period_s / args.speedup)
        if stop.is_set():
            raise ReplayInterrupted(records)
        return records
    finally:
        if watcher is not None:
            watcher.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await watcher
        await runtime.stop()
        await rig.stop()


class ReplayInterrupted(ServiceError):
    """SIGINT or SIGTERM stopped the replay; ``records``: what it identified until then (stored). Not a
    failure: ``main`` writes the records out and exits 130."""

    def __init__(self, records: list[IdentificationRecord]) -> None:
        super().__init__(f"interrupted after {len(records)} identifications")
        self.records = records


def install_stop_signals(stop: asyncio.Event) -> None:
    """SIGINT and SIGTERM set ``stop`` (handlers on the running loop: a terminal's Ctrl-C, ``kill``)."""
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        with contextlib.suppress(NotImplementedError, RuntimeError):
            loop.add_signal_handler(sig, stop.set)


async def _sleep_unless(stop: asyncio.Event, seconds: float) -> None:
    with contextlib.suppress(TimeoutError):
        await asyncio.wait_for(stop.wait(), timeout=max(0.0, seconds))


class RecordLines:
    """Prints the service's events and, after each, the identifications stored since, as ``chtc identify``
    prints them (records restored from an earlier run's database are not this replay's)."""

    def __init__(self, box: tuple[float, float] | None = None) -> None:
        self.service: SoftSensorService | None = None
        self.printed: set[int] = set()
        self.box = box  # the model's H search box: CI bounds beyond it print as identify prints them

    def follow(self, service: SoftSensorService | None) -> None:
        self.service = service
        if service is not None:
            self.printed |= {r.id for r in service.view.records}

    def event(self, message: str) -> None:
        print(message, flush=True)
        self.print_new()

    def print_new(self) -> None:
        if self.service is None:
            return
        for r in sorted(self.service.view.records, key=lambda r: r.id):
            if r.id not in self.printed:
                self.printed.add(r.id)
                print(format_record(r, self.box), flush=True)


class GridClock:
    """``clock`` snapped to the nearest instant ``origin + k·period_s``: the replay's sample stamps.

    The acquisition samples on that grid (``_begin_in_phase``), but the event loop wakes it a little late, by
    more on a loaded machine; stamped with the late time, the live state was stepped over 10 ± δ s and later
    windows started from a slightly different field than ``chtc identify``'s, which moved poorly identified H
    far along the fit's flat directions. Snapped, the stamps are exactly identify's (a wake-up later than
    half a period still snaps to the wrong instant, and one later than 0.7 periods sees the next row).
    """

    def __init__(self, clock: Callable[[], datetime], *, origin: datetime, period_s: float) -> None:
        self.clock, self.origin, self.period_s = clock, origin, period_s

    def __call__(self) -> datetime:
        k = round((self.clock() - self.origin).total_seconds() / self.period_s)
        return self.origin + timedelta(seconds=k * self.period_s)


async def _begin_in_phase(
    replay: Replay, clock: ScaledClock, period_wall_s: float, *, phase: float = REPLAY_PHASE
) -> None:
    """Start the replay so the acquisition samples ``phase`` of a period after each row it serves.

    The sampler ticks every period from when it started (just now); beginning the replay ``1 − phase``
    periods before its next tick makes every sample see the served row of the grid point ``phase`` periods
    earlier (held for a whole period), with the speed at the sample instant. Half a period on either side:
    a DAQ poll up to half a period late, or a sampler wake-up up to half a period late (``GridClock`` snaps
    the stamp back), still gives identify's sample.
    """
    await asyncio.sleep(0)  # let the sampler task take its first time reading
    await asyncio.sleep((1.0 - phase) * period_wall_s)
    clock.start(at=datetime.fromtimestamp(replay.t_ref, tz=UTC))
    replay.begin()


def main(args: argparse.Namespace) -> int:
    from drivers.logs import LogFormatError
    from service.commands.demo import log_spindle_default, quiet_third_party_logs
    from service.settings import SettingsError, load_settings

    quiet_third_party_logs()
    try:
        settings = load_settings(args.config)
        check_log_arguments(args.csv, args.can)
        if args.database_url is not None:
            settings = override(settings, "database", url=args.database_url)
        api = {k: v for k, v in (("host", args.host), ("port", args.port)) if v is not None}
        settings = override(settings, "api", **api) if api else settings
        url_option = "--database-url" if args.database_url is not None else "database.url"
        check_database_url(settings.database.url, url_option)
        if args.api:
            check_listen(settings.api.host, settings.api.port)
    except (SettingsError, CommandError) as err:
        print(f"chtc replay: {err}", file=sys.stderr)
        return 2
    log_spindle_default(settings)
    growth = GrowthLog()
    interrupted = False
    try:
        records = asyncio.run(run_replay(args, settings, growth=growth))
    except (LogFormatError, OSError) as err:
        print(f"chtc replay: {err}", file=sys.stderr)
        return 2
    except ReplayInterrupted as stop:
        records, interrupted = stop.records, True
        print(f"chtc replay: {stop}; writing them out", file=sys.stderr)
    write_out(args.out, records, growth)
    print(summary_line(records))
    done = "replay interrupted" if interrupted else "replay done"
    print(f"{done}: {len(records)} identifications -> {args.out} and the database")
    if args.growth_out is not None:
        growth.write(args.growth_out)
        print(f"growth history: {len(growth.rows)} rows -> {args.growth_out}")
    return 130 if interrupted else 0
