"""``chtc simulate``: serve the simulated Modbus DAQ and CAN sensor node, driven by the plant or a replay.

Default: the Modbus DAQ on ``127.0.0.1:5020`` and the CAN node behind a python-can-remote hub on
``ws://127.0.0.1:54701/`` (connect with ``can.Bus(interface="remote", channel="ws://127.0.0.1:54701/")``).
The hub (``can_remote.RemoteServer``) runs in this process on a thread; every client gets a ``virtual`` bus
on a private channel that the node also sends on. With another ``--can-interface`` (``socketcan``,
``virtual``) the node sends on that bus directly.

The timeline is the virtual plant (``model.plant.VirtualPlant``) run over ``--profile``: a named profile
(``steps``: 3000 → 4000 → 5000 rpm, 60 min each; ``short``: 10 min each) or a TOML/JSON file with a list
of segments (``duration_s``, ``speed_rpm``, ``torque_nm``, ``ambient_c``; TOML: ``[[segment]]`` tables).
``--replay-csv`` / ``--replay-can`` serve recorded logs instead (``--speedup`` is then the replay speed).
Stops on Ctrl-C or after ``--duration`` wall seconds.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import logging
import os
import sys
import tomllib
from collections.abc import AsyncIterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import can

from drivers.errors import DriverError
from drivers.registers import RegisterMap, default_register_map, load_register_map
from drivers.sim.can_hub import CanHub
from drivers.sim.can_node import SimulatedCanNode
from drivers.sim.faults import FaultController, FaultSpecError, parse_fault
from drivers.sim.modbus_server import SimulatedDaq
from drivers.sim.replay import Replay
from drivers.sim.source import TimelineSource
from service.errors import ServiceError

if TYPE_CHECKING:
    from model.plant import PlantRun

SEGMENT_KEYS = ("duration_s", "speed_rpm", "torque_nm", "ambient_c")
NAMED_PROFILES: dict[str, list[tuple[float, float, float, float]]] = {
    "steps": [(3600.0, 3000.0, 5.0, 23.2), (3600.0, 4000.0, 6.0, 21.8), (3600.0, 5000.0, 8.0, 22.0)],
    "short": [(600.0, 3000.0, 5.0, 23.2), (600.0, 4000.0, 6.0, 21.8), (600.0, 5000.0, 8.0, 22.0)],
}


class ProfileError(ServiceError, ValueError):
    """A profile name or file is invalid; the message names the file, segment and key."""


@dataclass(frozen=True, kw_only=True)
class ProfileSegment:
    """One operating segment: duration s, speed rpm, torque N·m, ambient °C (as ``model.plant.Segment``)."""

    duration_s: float
    speed_rpm: float
    torque_nm: float
    ambient_c: float


def load_profile(text: str) -> list[ProfileSegment]:
    """A named profile (``steps``, ``short``) or a TOML/JSON file of segments."""
    if text in NAMED_PROFILES:
        return [_named(seg) for seg in NAMED_PROFILES[text]]
    path = Path(text)
    if not path.is_file():
        raise ProfileError(f"profile {text!r}: not a named profile ({', '.join(NAMED_PROFILES)}) nor a file")
    try:
        raw: object = (
            json.loads(path.read_text())
            if path.suffix == ".json"
            else tomllib.loads(path.read_text())["segment"]
        )
    except (OSError, ValueError, KeyError, tomllib.TOMLDecodeError) as err:
        raise ProfileError(f"{path}: cannot read profile ({err}); expected a list of segments") from err
    if not isinstance(raw, list) or not raw:
        raise ProfileError(f"{path}: expected a non-empty list of segments")
    return [_segment(path, i, item) for i, item in enumerate(raw)]


def _named(seg: Sequence[float]) -> ProfileSegment:
    duration, speed, torque, ambient = seg
    return ProfileSegment(duration_s=duration, speed_rpm=speed, torque_nm=torque, ambient_c=ambient)


def _segment(path: Path, i: int, item: object) -> ProfileSegment:
    if not isinstance(item, dict):
        raise ProfileError(f"{path}: segment[{i}] is not a table/object")
    values = []
    for key in SEGMENT_KEYS:
        try:
            values.append(float(item[key]))
        except (KeyError, TypeError, ValueError) as err:
            raise ProfileError(f"{path}: segment[{i}].{key}: missing or not a number") from err
    if values[0] <= 0:
        raise ProfileError(f"{path}: segment[{i}].duration_s: must be > 0")
    return _named(values)


def plant_timeline(profile: Sequence[ProfileSegment], *, seed: int, dt_s: float, noise_c: float) -> PlantRun:
    """Run the virtual plant over ``profile`` (returns a ``model.plant.PlantRun``)."""
    from model.geometry import load_spindle
    from model.plant import Segment, VirtualPlant

    plant = VirtualPlant(load_spindle(), noise_c=noise_c, seed=seed)
    segments = [Segment(s.duration_s, s.speed_rpm, s.torque_nm, s.ambient_c) for s in profile]
    return plant.run(segments, dt_s=dt_s)


# ------------------------------------------------------------------------------------------------ CAN side
@contextlib.asynccontextmanager
async def can_bus(args: argparse.Namespace) -> AsyncIterator[tuple[can.BusABC | None, str]]:
    """The bus the node sends on, and a description of where it can be heard."""
    if args.no_can:
        yield None, "CAN: off"
        return
    hub = None
    if args.can_interface == "remote":
        channel = f"chtc-sim-{os.getpid()}"
        hub = CanHub(args.can_channel, channel)
        hub.start()
        bus = can.Bus(interface="virtual", channel=channel, ignore_config=True)
        where = f"python-can-remote hub {hub.url} (interface 'remote', channel '{hub.url}')"
    else:
        bus = can.Bus(interface=args.can_interface, channel=args.can_channel, ignore_config=True)
        where = f"interface '{args.can_interface}', channel '{args.can_channel}'"
    try:
        yield bus, where
    finally:
        bus.shutdown()
        if hub is not None:
            await asyncio.to_thread(hub.stop)


# ----------------------------------------------------------------------------------------------- serving
async def _serve(args: argparse.Namespace) -> int:
    faults = FaultController([parse_fault(f) for f in args.fault])
    reg_map = load_register_map(args.register_map) if args.register_map else default_register_map()
    async with can_bus(args) as (bus, where):
        if args.replay_csv:
            return await _serve_replay(args, bus, where=where, reg_map=reg_map, faults=faults)
        return await _serve_plant(args, bus, where=where, reg_map=reg_map, faults=faults)


async def _serve_plant(
    args: argparse.Namespace,
    bus: can.BusABC | None,
    *,
    where: str,
    reg_map: RegisterMap,
    faults: FaultController,
) -> int:
    profile = load_profile(args.profile)
    total = sum(s.duration_s for s in profile)
    print(f"computing the virtual plant: {len(profile)} segments, {total:.0f} s simulated ...", flush=True)
    run = await asyncio.to_thread(plant_timeline, profile, seed=args.seed, dt_s=args.dt, noise_c=args.noise)
    source = TimelineSource(run, speedup=args.speedup, loop=args.loop)
    daq = SimulatedDaq(
        source,
        host=args.modbus_host,
        port=args.modbus_port,
        register_map=reg_map,
        faults=faults,
        sample_period_s=args.sample_period,
    )
    node = SimulatedCanNode(source, bus=bus, faults=faults) if bus is not None else None
    source.start()
    async with contextlib.AsyncExitStack() as stack:
        if not args.no_modbus:
            await stack.enter_async_context(daq)
        if node is not None:
            await stack.enter_async_context(node)
        what = f"virtual plant, profile '{args.profile}', {total:.0f} s simulated"
        _announce(args, daq, where=where, what=what, faults=faults)
        print(f"at {args.speedup:g}x the timeline lasts {total / args.speedup:.0f} s wall", flush=True)
        await _wait(args.duration)
    return 0


async def _serve_replay(
    args: argparse.Namespace,
    bus: can.BusABC | None,
    *,
    where: str,
    reg_map: RegisterMap,
    faults: FaultController,
) -> int:
    replay = Replay(
        args.replay_csv,
        args.replay_can,
        bus=bus,
        speed=args.speedup,
        host=args.modbus_host,
        port=args.modbus_port,
        register_map=reg_map,
        faults=faults,
    )
    async with replay:
        what = f"replay of {args.replay_csv}" + (f" + {args.replay_can}" if args.replay_can else "")
        _announce(args, replay.daq, where=where, what=what, faults=faults)
        print(f"replay lasts {replay.duration_s:.1f} s wall at {args.speedup:g}x", flush=True)
        await _wait(args.duration if args.duration is not None else replay.duration_s + 1.0)
    return 0


def _announce(
    args: argparse.Namespace, daq: SimulatedDaq, *, where: str, what: str, faults: FaultController
) -> None:
    if not args.no_modbus:
        m = daq.register_map
        print(
            f"Modbus TCP DAQ on {daq.host}:{daq.port} (unit {m.unit_id}, {m.n_channels} channels, "
            f"input registers {m.entries[0].address}-{m.entries[-1].last_address}, read-only)",
            flush=True,
        )
    print(f"CAN SpindleStatus 0x181 every 10 ms: {where}" if not args.no_can else where, flush=True)
    print(f"timeline: {what}, speed-up {args.speedup:g}x", flush=True)
    for text in args.fault:
        print(f"fault: {parse_fault(text)}", flush=True)
    print("Ctrl-C to stop" + (f" (or after {args.duration:g} s)" if args.duration else ""), flush=True)


async def _wait(duration_s: float | None) -> None:
    if duration_s is None:
        await asyncio.Event().wait()
    else:
        await asyncio.sleep(duration_s)


# ------------------------------------------------------------------------------------------------- CLI
def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``chtc simulate``."""
    parser.add_argument("--modbus-host", default="127.0.0.1", help="DAQ listen address")
    parser.add_argument("--modbus-port", type=int, default=5020, help="0: any free port (printed)")
    parser.add_argument(
        "--register-map", type=Path, help="register map TOML (default: the device contract, docs/drivers.md)"
    )
    parser.add_argument("--sample-period", type=float, default=0.1, help="DAQ sample period, wall s")
    parser.add_argument("--can-interface", default="remote", help="remote (hub), virtual, socketcan ...")
    parser.add_argument("--can-channel", default="ws://127.0.0.1:54701/", help="hub URL or bus channel")
    parser.add_argument("--no-modbus", action="store_true")
    parser.add_argument("--no-can", action="store_true")
    parser.add_argument("--speedup", type=float, default=1.0, help="simulated s per wall s (replay speed)")
    parser.add_argument(
        "--profile", default="steps", help=f"{' | '.join(NAMED_PROFILES)} | FILE.toml | FILE.json"
    )
    parser.add_argument("--seed", type=int, default=0, help="plant noise seed")
    parser.add_argument("--noise", type=float, default=0.15, help="plant sensor noise, °C (1 sigma)")
    parser.add_argument("--dt", type=float, default=10.0, help="plant time step, s")
    parser.add_argument("--loop", action="store_true", help="start the profile again at its end")
    parser.add_argument(
        "--duration", type=float, default=None, help="stop after this many wall seconds (default: Ctrl-C)"
    )
    parser.add_argument(
        "--fault",
        action="append",
        default=[],
        metavar="KIND[:ch=N+M,at=S,for=S,value=V]",
        help="inject a fault (repeatable), e.g. open:ch=5,at=30,for=60 | drop:at=10,for=10 | counter-gap",
    )
    parser.add_argument(
        "--replay-csv",
        type=Path,
        help="serve a recorded temperature CSV instead of the plant (default: the plant)",
    )
    parser.add_argument(
        "--replay-can",
        type=Path,
        help="send a recorded CAN log (with --replay-csv; default: no CAN frames in a replay)",
    )


def main(args: argparse.Namespace) -> int:
    """Run ``chtc simulate``."""
    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)  # injected faults make pymodbus log noisily
    if args.replay_can and not args.replay_csv:
        print("chtc simulate: --replay-can needs --replay-csv", file=sys.stderr)
        return 2
    try:
        for text in args.fault:
            parse_fault(text)
        return asyncio.run(_serve(args))
    except (FaultSpecError, ProfileError, DriverError, can.CanError, OSError) as err:
        print(f"chtc simulate: {err}", file=sys.stderr)
        return 1
