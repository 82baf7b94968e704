"""``chtc replay``: recorded logs -> simulated devices -> the unchanged service; every identification saved.

The simulated Modbus DAQ serves the temperature CSV and the CAN log is replayed on a private virtual CAN
channel (``drivers.sim.replay``), at ``--speedup`` recorded seconds per wall second. The service runs exactly
as in production (drivers, ring buffer, detector, scheduler, worker process, database writer); its clock
reads the recorded time, so stored timestamps are the log's. When the log ends (plus the time for running
identifications) every identification is in the database and in ``--out`` (JSON, or CSV by suffix).

The DAQ serves the recording reduced to the rows the acquisition samples (``write_acquisition_csv``: one row
per ``acquisition.sample_period_s``, the newest recorded row at each sample instant), and the acquisition is
started in phase with them, so a replay sees the same samples as ``chtc identify`` on the same files, also for
real-time recordings with one jittered row per second; see docs/service.md for what can still differ.
"""

from __future__ import annotations

import argparse
import asyncio
import csv
import json
import sys
import tempfile
import time
from collections.abc import Callable
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from drivers.sim.replay import Replay
    from service.engine.runtime import ScaledClock
    from service.serve.interface import IdentificationRecord
    from service.settings import Settings

from service.commands._common import CommandError, check_listen, override, port_number, positive_float
from service.commands.identify import num, record_dict
from service.sim.logsamples import REPLAY_PHASE, write_acquisition_csv


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


def write_out(path: Path, records: list[IdentificationRecord]) -> None:
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
        rows = [record_dict(r) for r in records]
        path.write_text(json.dumps(rows, indent=2) + "\n", encoding="utf-8")


async def run_replay(args: argparse.Namespace, settings: Settings) -> list[IdentificationRecord]:
    with tempfile.TemporaryDirectory(prefix="chtc-replay-") as tmp:
        served = Path(tmp) / "acquired.csv"
        period_s = settings.acquisition.sample_period_s
        await asyncio.to_thread(write_acquisition_csv, args.csv, args.can, served, period_s=period_s)
        return await _replay(args, settings, served)


async def _replay(
    args: argparse.Namespace, settings: Settings, served_csv: Path
) -> list[IdentificationRecord]:
    from service.engine.runtime import Runtime, ScaledClock
    from service.sim.simrig import SimAddress, make_drivers, replay_rig

    clock = ScaledClock(args.speedup)
    period_s = settings.acquisition.sample_period_s
    runtime = Runtime(settings=settings, clock=clock, on_event=lambda m: print(m, flush=True))
    await asyncio.to_thread(runtime.load)
    address = SimAddress.free(speedup=args.speedup)
    rig = await replay_rig(served_csv, args.can, address=address, begin=False)
    replay = rig.replay
    assert replay is not None  # a replay rig
    origin = datetime.fromtimestamp(replay.t_ref + REPLAY_PHASE * period_s, tz=UTC)
    runtime.sample_clock = GridClock(clock, origin=origin, period_s=period_s)
    daq, can_sensor = make_drivers(settings, address, clock=clock)
    try:
        await runtime.start(daq=daq, can=can_sensor, api=args.api)
        if args.api:
            await runtime.wait_api()
            print(f"dashboard: {runtime.url}   (API: {runtime.url}api/v1/chtc)", flush=True)
        await _begin_in_phase(replay, clock, settings.acquisition.sample_period_s / args.speedup)
        await asyncio.sleep(replay.duration_s + 2.0 * settings.acquisition.sample_period_s / args.speedup)
        deadline = time.monotonic() + args.grace
        service = runtime.service
        assert service is not None
        while service.view.running_job is not None and time.monotonic() < deadline:
            await asyncio.sleep(0.1)
        return list(reversed(service.view.records))
    finally:
        await runtime.stop()
        await rig.stop()


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
    from service.commands.demo import quiet_third_party_logs
    from service.settings import SettingsError, load_settings

    quiet_third_party_logs()
    try:
        settings = load_settings(args.config)
        if args.database_url is not None:
            settings = override(settings, "database", url=args.database_url)
        api = {k: v for k, v in (("host", args.host), ("port", args.port)) if v is not None}
        settings = override(settings, "api", **api) if api else settings
        if args.api:
            check_listen(settings.api.host, settings.api.port)
    except (SettingsError, CommandError) as err:
        print(f"chtc replay: {err}", file=sys.stderr)
        return 2
    try:
        records = asyncio.run(run_replay(args, settings))
    except (LogFormatError, OSError) as err:
        print(f"chtc replay: {err}", file=sys.stderr)
        return 2
    write_out(args.out, records)
    ok = sum(r.outcome == "ok" for r in records)
    print(f"replay done: {len(records)} identifications ({ok} ok) -> {args.out} and the database")
    return 0
