"""In-process simulated devices for ``chtc replay`` and the end-to-end tests (``chtc demo`` runs its own in a
child process: ``simulator.rigproc``).

A rig is the simulated Modbus DAQ (``drivers.sim.modbus_server.SimulatedDaq``) on a free loopback port and
the CAN side on a private python-can ``virtual`` channel: either the simulated sensor node driven by a
plant timeline, or a recorded CAN log replayed (``drivers.sim.replay``). ``drivers(settings, rig)`` builds the
service's real drivers pointed at it, with time-outs scaled to the speed-up.
"""

from __future__ import annotations

import contextlib
import itertools
import os
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import can

from service.host.runtime import ScaledClock, free_port

if TYPE_CHECKING:
    from drivers.can_sensor import CanSpindleSensor
    from drivers.modbus_daq import ModbusDaq
    from drivers.sim.can_node import SimulatedCanNode
    from drivers.sim.modbus_server import SimulatedDaq
    from drivers.sim.replay import Replay
    from drivers.sim.source import Timeline
    from service.settings import Settings

__all__ = ["SimAddress", "SimRig", "make_drivers", "plant_rig", "replay_rig"]

_channels = itertools.count(1)


def _channel() -> str:
    return f"chtc-sim-{os.getpid()}-{next(_channels)}"


@dataclass(frozen=True, kw_only=True)
class SimAddress:
    """Where a rig will serve: DAQ ``host:port`` and the CAN ``channel`` (chosen before it starts): a
    private ``virtual`` channel in this process, or a python-can-remote hub's URL (``can_interface="remote"``:
    a rig in another process, ``simulator.rigproc``)."""

    host: str
    port: int
    channel: str
    speedup: float
    can_interface: str = "virtual"

    @classmethod
    def free(cls, *, speedup: float, host: str = "127.0.0.1") -> SimAddress:
        return cls(host=host, port=free_port(host), channel=_channel(), speedup=float(speedup))


@dataclass(kw_only=True)
class SimRig:
    """Running simulated devices: DAQ on ``host:port``, CAN frames on virtual ``channel``."""

    host: str
    port: int
    channel: str
    speedup: float
    daq_server: SimulatedDaq
    can_interface: str = "virtual"
    can_node: SimulatedCanNode | None = None
    replay: Replay | None = None
    bus: can.BusABC | None = None

    def plant_time_s(self) -> float:
        """Simulated time of the timeline being served, s (0 at its first row)."""
        source = self.replay.source if self.replay is not None else self.daq_server.source
        return float(source.sim_time_s() - source.run.times_s[0])

    async def stop(self) -> None:
        if self.replay is not None:
            await self.replay.stop()
        else:
            if self.can_node is not None:
                await self.can_node.stop()
            await self.daq_server.stop()
        if self.bus is not None:
            with contextlib.suppress(Exception):
                self.bus.shutdown()


async def plant_rig(timeline: Timeline, *, address: SimAddress, daq_period_s: float = 1.0) -> SimRig:
    """The DAQ and the CAN node playing ``timeline`` (a ``model.plant.PlantRun`` or any Timeline) from now on.

    Start it after the service: the plant's first row is served once the service is listening, as when a
    machine is switched on next to a running soft sensor. The simulated DAQ converts every ``daq_period_s``
    plant seconds (interpolating the plant's 10 s rows), so the temperatures the acquisition reads are at
    most about a second older than the speed and torque it pairs them with.
    """
    from drivers.sim.can_node import SimulatedCanNode
    from drivers.sim.modbus_server import SimulatedDaq
    from drivers.sim.source import TimelineSource

    a = address
    source = TimelineSource(timeline, speedup=a.speedup)
    bus = can.Bus(interface="virtual", channel=a.channel, ignore_config=True)
    daq = SimulatedDaq(source, host=a.host, port=a.port, sample_period_s=daq_period_s / a.speedup)
    node = SimulatedCanNode(source, bus=bus)
    source.start()
    await daq.start()
    await node.start()
    return SimRig(
        host=a.host, port=a.port, channel=a.channel, speedup=a.speedup, daq_server=daq, can_node=node, bus=bus
    )


async def replay_rig(
    csv_path: str | Path, can_path: str | Path | None, *, address: SimAddress, begin: bool = True
) -> SimRig:
    """Recorded logs served by the simulated DAQ (row by row, held) and replayed on a virtual CAN channel."""
    from drivers.sim.replay import Replay

    a = address
    bus = can.Bus(interface="virtual", channel=a.channel, ignore_config=True)
    replay = Replay(csv_path, can_path, bus=bus, speed=a.speedup, host=a.host, port=a.port)
    await replay.listen()
    if begin:
        replay.begin()
    return SimRig(
        host=a.host,
        port=a.port,
        channel=a.channel,
        speedup=a.speedup,
        daq_server=replay.daq,
        replay=replay,
        bus=bus,
    )


def make_drivers(
    settings: Settings, rig: SimAddress | SimRig, *, clock: ScaledClock
) -> tuple[ModbusDaq, CanSpindleSensor]:
    """The service's Modbus and CAN drivers connected to ``rig`` (wall-clock limits scaled to speed-up)."""
    from drivers.can_sensor import CanSpindleSensor
    from drivers.modbus_daq import ModbusDaq

    period_wall = settings.acquisition.sample_period_s / rig.speedup
    daq = ModbusDaq(
        rig.host,
        rig.port,
        timeout_s=settings.modbus.timeout_s,
        stale_after_s=max(2.0, 5.0 * period_wall),
        stuck_samples=None,
        now=clock,
    )
    can_sensor = CanSpindleSensor(
        interface=rig.can_interface,
        channel=rig.channel,
        stale_after_s=max(1.0, 3.0 * period_wall),
        batch_s=settings.can.batch_s,
        now=clock,
    )
    return daq, can_sensor
