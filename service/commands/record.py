"""``chtc record``: record live devices into a temperature CSV and a CAN log.

The DAQ is polled with the Modbus driver (``drivers.modbus_daq.ModbusDaq``); a CSV row is written for every
poll that shows a new device sample (the DAQ counter advanced), with the driver's UTC receive time. The CAN
bus is logged raw (every frame as received, including unknown IDs and bad frames, so a replay reproduces
faults too) through a ``can.Notifier``; frames are also decoded with ``drivers.can_codec`` only to count
decode errors for the progress line. Files: ``DIR/temperatures.csv`` and ``DIR/can.<format>``.

Time stamps are the source's time: with ``--speedup S`` (a simulator running ``chtc simulate --speedup S``)
every CSV row and every CAN frame is stamped ``t0 + S × (receive time − t0)``, ``t0`` the recording's start
(UTC), so a sped-up simulation is recorded in its own (simulated) time and ``chtc identify``/``chtc replay``
see the durations the plant ran. ``S`` = 1 (the default) is the wall clock, for real devices. The DAQ must be
polled often enough for the simulated sample period: ``--interval`` is wall seconds (one poll per
``interval × S`` simulated seconds).

Stops after ``--duration`` wall seconds or on Ctrl-C; files are closed (BLF/ASC footers written) either way.
"""

from __future__ import annotations

import argparse
import asyncio
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path

import can

from drivers.can_codec import decode_frame
from drivers.errors import DeviceError, FrameError
from drivers.logs import CAN_LOG_SUFFIXES, CanLogWriter, LogFormatError, TemperatureCsvWriter
from drivers.modbus_daq import ModbusDaq
from drivers.registers import RegisterMap, default_register_map, load_register_map
from service.commands._common import positive_float

CSV_NAME = "temperatures.csv"
CAN_STEM = "can"


@dataclass(frozen=True, kw_only=True)
class SourceTime:
    """Receive (wall) time -> the source's time: ``t0 + speedup·(t − t0)``, POSIX s; speedup 1: wall time."""

    t0: float
    speedup: float = 1.0
    wall: Callable[[], float] = time.time

    def of(self, wall_s: float) -> float:
        """The source's time (POSIX s) of a receive time ``wall_s`` (POSIX s)."""
        return self.t0 + self.speedup * (wall_s - self.t0)

    def now(self) -> datetime:
        """The source's time now, UTC (the DAQ driver's clock)."""
        return datetime.fromtimestamp(self.of(self.wall()), tz=UTC)


@dataclass(kw_only=True)
class RecordStats:
    """What a recording has collected so far."""

    elapsed_s: float = 0.0
    polls: int = 0
    rows: int = 0
    daq_errors: int = 0
    frames: int = 0
    frame_errors: int = 0
    write_errors: int = 0
    last_error: str = ""

    def line(self) -> str:
        """One progress line, units included."""
        err = f"  last error: {self.last_error}" if self.last_error else ""
        return (
            f"t={self.elapsed_s:7.1f} s  rows={self.rows}  polls={self.polls}  daq_errors={self.daq_errors}  "
            f"can_frames={self.frames}  can_frame_errors={self.frame_errors}  "
            f"write_errors={self.write_errors}{err}"
        )


class _CanRecorder(can.Listener):
    """Writes every received frame to the log and counts frames that do not decode."""

    def __init__(
        self, *, writer: CanLogWriter, stats: RecordStats, source_time: SourceTime | None = None
    ) -> None:
        self.writer, self.stats, self.source_time = writer, stats, source_time
        self.closed = False

    def on_message_received(self, msg: can.Message) -> None:
        if self.closed:
            return
        if self.source_time is not None:
            msg.timestamp = self.source_time.of(msg.timestamp)
        try:
            self.writer.write(msg)
        except LogFormatError as err:
            self.stats.write_errors += 1
            self.stats.last_error = str(err)
            return
        self.stats.frames += 1
        try:
            decode_frame(msg.arbitration_id, bytes(msg.data), is_extended_id=msg.is_extended_id)
        except FrameError as err:
            self.stats.frame_errors += 1
            self.stats.last_error = str(err)

    def on_error(self, exc: Exception) -> None:
        self.stats.last_error = f"CAN bus error: {exc}"

    def stop(self) -> None:
        """The writer is closed by ``record``."""


async def record(
    *,
    daq: ModbusDaq | None,
    bus: can.BusABC | None,
    csv_path: Path | None,
    can_path: Path | None,
    duration_s: float | None,
    interval_s: float = 1.0,
    progress: Callable[[RecordStats], None] | None = None,
    progress_every_s: float = 5.0,
    clock: Callable[[], float] = time.monotonic,
    source_time: SourceTime | None = None,
) -> RecordStats:
    """Record ``daq`` into ``csv_path`` and ``bus`` into ``can_path`` for ``duration_s`` s (None: until
    cancelled). ``source_time`` restamps CAN frames in the source's time (give the DAQ driver the same clock
    as its ``now``). Returns the final statistics; files are closed on every exit path."""
    stats = RecordStats()
    csv_writer = TemperatureCsvWriter(csv_path) if daq is not None and csv_path is not None else None
    can_writer = CanLogWriter(can_path) if bus is not None and can_path is not None else None
    notifier, recorder = None, None
    if bus is not None and can_writer is not None:
        recorder = _CanRecorder(writer=can_writer, stats=stats, source_time=source_time)
        notifier = can.Notifier(bus, [recorder], timeout=0.05, loop=asyncio.get_running_loop())
    start = clock()
    next_progress = progress_every_s
    try:
        while duration_s is None or clock() - start < duration_s:
            tick = clock()
            if daq is not None and csv_writer is not None:
                await _poll_once(daq, csv_writer, stats)
            stats.elapsed_s = clock() - start
            if progress is not None and stats.elapsed_s >= next_progress:
                progress(stats)
                next_progress += progress_every_s
            wait = interval_s - (clock() - tick)
            if duration_s is not None:
                wait = min(wait, duration_s - (clock() - start))
            await asyncio.sleep(max(wait, 0.0))
    finally:
        if notifier is not None:
            await asyncio.to_thread(notifier.stop, 1.0)
        if recorder is not None:
            recorder.closed = (
                True  # frames still queued on the loop are dropped, not written to a closed file
            )
        if can_writer is not None:
            can_writer.close()
        if csv_writer is not None:
            csv_writer.close()
        stats.elapsed_s = clock() - start
    return stats


async def _poll_once(daq: ModbusDaq, writer: TemperatureCsvWriter, stats: RecordStats) -> None:
    stats.polls += 1
    try:
        reading = await daq.read()
    except DeviceError as err:
        stats.daq_errors += 1
        stats.last_error = str(err)
        return
    if reading.new_sample:
        writer.write(
            reading.t,
            temps_c=reading.temps_c,
            ambient_c=reading.ambient_c,
            status=reading.status,
            counter=reading.counter,
        )
        stats.rows += 1


# ------------------------------------------------------------------------------------------------- CLI
def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``chtc record``."""
    parser.add_argument("--out", type=Path, required=True, help="output directory (created if missing)")
    parser.add_argument("--modbus-host", default="127.0.0.1", help="DAQ address")
    parser.add_argument("--modbus-port", type=int, default=5020, help="DAQ port")
    parser.add_argument(
        "--register-map", type=Path, help="register map TOML (default: the device contract, docs/drivers.md)"
    )
    parser.add_argument("--modbus-timeout", type=float, default=1.0, help="per-request timeout, s")
    parser.add_argument("--interval", type=float, default=1.0, help="DAQ poll period, wall s (default 1)")
    parser.add_argument(
        "--speedup",
        type=positive_float,
        default=1.0,
        help="the source's seconds per wall second: the simulator's --speedup; stamps are the source's time",
    )
    parser.add_argument("--can-interface", default="remote", help="python-can interface (default remote)")
    parser.add_argument("--can-channel", default="ws://127.0.0.1:54701/", help="python-can channel")
    parser.add_argument(
        "--can-format",
        default="blf",
        choices=[s.lstrip(".") for s in CAN_LOG_SUFFIXES],
        help="CAN log format",
    )
    parser.add_argument("--no-modbus", action="store_true", help="record CAN only")
    parser.add_argument("--no-can", action="store_true", help="record temperatures only")
    parser.add_argument(
        "--duration", type=float, default=None, help="seconds to record (default: until Ctrl-C)"
    )
    parser.add_argument("--progress-every", type=float, default=5.0, help="progress line period, s")


def _register_map(path: Path | None) -> RegisterMap:
    return load_register_map(path) if path is not None else default_register_map()


async def _amain(args: argparse.Namespace) -> RecordStats:
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    csv_path = None if args.no_modbus else out / CSV_NAME
    can_path = None if args.no_can else out / f"{CAN_STEM}.{args.can_format}"
    source_time = SourceTime(t0=time.time(), speedup=args.speedup)
    daq = None
    if not args.no_modbus:
        daq = ModbusDaq(
            args.modbus_host,
            args.modbus_port,
            register_map=_register_map(args.register_map),
            timeout_s=args.modbus_timeout,
            now=source_time.now,
        )
    bus = None
    if not args.no_can:
        bus = can.Bus(interface=args.can_interface, channel=args.can_channel, ignore_config=True)
    print(f"recording to {csv_path or '-'} and {can_path or '-'}; Ctrl-C to stop", flush=True)
    try:
        return await record(
            daq=daq,
            bus=bus,
            csv_path=csv_path,
            can_path=can_path,
            duration_s=args.duration,
            interval_s=args.interval,
            progress=lambda s: print(s.line(), flush=True),
            progress_every_s=args.progress_every,
            source_time=source_time if args.speedup != 1.0 else None,
        )
    finally:
        if daq is not None:
            await daq.close()
        if bus is not None:
            bus.shutdown()


def main(args: argparse.Namespace) -> int:
    """Run ``chtc record``; exit code 0 on success, 1 if nothing could be recorded."""
    try:
        stats = asyncio.run(_amain(args))
    except (can.CanError, OSError, ValueError) as err:
        print(f"chtc record: {err}", file=sys.stderr)
        return 1
    print(stats.line())
    print(f"done: {stats.rows} temperature rows, {stats.frames} CAN frames")
    return 0 if stats.rows or stats.frames else 1
