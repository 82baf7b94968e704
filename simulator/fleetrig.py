"""Simulated devices of many spindles in one process (``python -m simulator.fleetrig``; bench fleet).

Each spindle has its own simulated Modbus DAQ (a pymodbus server on its own loopback port) and its own CAN
node behind its own python-can-remote hub (``drivers.sim.can_hub``), both at their real rates (the DAQ
converts every second, the node sends SpindleStatus every 10 ms), so the soft sensor reaches them exactly as
it reaches real devices. They play virtual-plant runs (``simulator.endless``: random duty cycles on the
plant's own mesh and step) of ``--plants`` seeds; spindle i plays plant ``i % plants``, so the spindles of
one plant change speed at the same moments, as a cell does.

Input: one JSON object on the command line: ``{"host", "spindles", "plants", "hours", "seed"}``. Every
device binds a port of its own choosing (port 0: no race with other processes between choosing and
binding). Output: one line ``ready {"modbus_ports": [...], "can_ports": [...]}`` on stdout once every device
serves (progress on stderr). It stops at end of file on stdin (the parent closed it or died) or on SIGTERM.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import os
import signal
import sys
from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from simulator.endless import PlantRows

__all__ = ["FleetRigPlan", "main"]


@dataclass(frozen=True, kw_only=True)
class FleetRigPlan:
    host: str
    spindles: int
    plants: int = 4
    hours: float = 1.0
    seed: int = 0

    def __post_init__(self) -> None:
        if self.spindles < 1 or self.plants < 1:
            raise ValueError(f"spindles and plants: at least 1, got {self.spindles}, {self.plants}")


def _plants(plan: FleetRigPlan) -> list[PlantRows]:
    from model.geometry import load_spindle
    from simulator.endless import EndlessPlant

    spec = load_spindle()
    rows: list[PlantRows] = []
    for k in range(min(plan.plants, plan.spindles)):
        plant = EndlessPlant(spec, seed=plan.seed + k, chunk_s=3600.0 * plan.hours, idle_s=300.0)
        rows.append(plant.next_chunk())
        print(f"fleetrig: plant {k + 1} computed ({plan.hours:g} h)", file=sys.stderr, flush=True)
    return rows


async def serve(plan: FleetRigPlan) -> None:
    import can

    from drivers.sim.can_hub import CanHub
    from drivers.sim.can_node import SimulatedCanNode
    from drivers.sim.modbus_server import SimulatedDaq
    from drivers.sim.source import TimelineSource

    rows = await asyncio.to_thread(_plants, plan)
    hubs, buses, daqs, nodes = [], [], [], []
    try:
        for i in range(plan.spindles):
            channel = f"fleetrig-{i}"
            hub = CanHub(f"ws://{plan.host}:0/", channel)
            hub.start()
            hubs.append(hub)
            bus = can.Bus(interface="virtual", channel=channel, ignore_config=True)
            buses.append(bus)
            source = TimelineSource(rows[i % len(rows)], speedup=1.0)
            source.start()
            daq = SimulatedDaq(source, host=plan.host, port=0, sample_period_s=1.0)
            await daq.start()
            daqs.append(daq)
            node = SimulatedCanNode(source, bus=bus)
            await node.start()
            nodes.append(node)
        ports = {"modbus_ports": [d.port for d in daqs], "can_ports": [h.port for h in hubs]}
        print("ready " + json.dumps(ports), flush=True)
        await _until_told_to_stop()
    finally:
        for node in nodes:
            with contextlib.suppress(Exception):
                await node.stop()
        for daq in daqs:
            with contextlib.suppress(Exception):
                await daq.stop()
        for bus in buses:
            bus.shutdown()
        for hub in hubs:
            with contextlib.suppress(Exception):
                await asyncio.to_thread(hub.stop)


async def _until_told_to_stop() -> None:
    loop = asyncio.get_running_loop()
    stop = asyncio.Event()
    with contextlib.suppress(NotImplementedError, RuntimeError):
        loop.add_signal_handler(signal.SIGTERM, stop.set)

    def on_stdin() -> None:
        if not os.read(sys.stdin.fileno(), 4096):  # end of file: the parent is gone
            loop.remove_reader(sys.stdin.fileno())
            stop.set()

    loop.add_reader(sys.stdin.fileno(), on_stdin)
    await stop.wait()


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if len(args) != 1:
        print("usage: python -m simulator.fleetrig '<plan JSON>'", file=sys.stderr)
        return 2
    plan = FleetRigPlan(**json.loads(args[0]))
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)
    asyncio.run(serve(plan))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
