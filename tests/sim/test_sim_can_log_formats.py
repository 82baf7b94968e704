"""PCAN-View ``.trc`` and ASAM MDF ``.mf4`` CAN logs work for identify (log → samples) and for replay (log → a
python-can virtual bus → the CAN driver), like the other formats."""

from __future__ import annotations

import asyncio
import uuid
from datetime import UTC, datetime, timedelta
from pathlib import Path

import can
import numpy as np
import pytest

from drivers.can_codec import encode_status
from drivers.can_sensor import CanReading, CanSpindleSensor
from drivers.logs import TemperatureCsvWriter, write_can_log
from drivers.logsamples import samples_from_logs
from drivers.sim.replay import Replay

T0 = datetime(2026, 3, 1, 12, 0, tzinfo=UTC)
SUFFIXES = [".trc", ".mf4"]


def _logs(tmp_path: Path, suffix: str) -> tuple[Path, Path]:
    csv_path, can_path = tmp_path / "t.csv", tmp_path / f"c{suffix}"
    with TemperatureCsvWriter(csv_path) as w:
        for i in range(5):
            w.write(T0 + timedelta(seconds=i), temps_c=np.full(32, 20.0 + i), ambient_c=21.0, counter=i)
    frames = [
        can.Message(
            timestamp=T0.timestamp() + 0.1 * k,
            arbitration_id=0x181,
            is_extended_id=False,
            data=encode_status(3000 + k, 5.0, k % 16, 0),
        )
        for k in range(45)
    ]
    write_can_log(can_path, frames)
    return csv_path, can_path


@pytest.mark.parametrize("suffix", SUFFIXES)
def test_identify_reads_speed_and_torque_from_the_log(tmp_path: Path, suffix: str) -> None:
    csv_path, can_path = _logs(tmp_path, suffix)
    got = samples_from_logs(csv_path, can_path)
    assert got.frames == 45 and got.bad_frames == 0
    speeds = [s.speed_rpm for s in got.samples]
    assert speeds == [3000.0, 3010.0, 3020.0, 3030.0, 3040.0]  # the frame at or just before each row
    assert all(s.can_ok and s.torque_nm == 5.0 for s in got.samples)


@pytest.mark.parametrize("suffix", SUFFIXES)
def test_replay_sends_the_logged_frames_to_the_driver(tmp_path: Path, suffix: str) -> None:
    csv_path, can_path = _logs(tmp_path, suffix)
    channel = f"replay-{uuid.uuid4().hex}"

    async def main() -> list[float]:
        bus = can.Bus(interface="virtual", channel=channel, ignore_config=True)
        try:
            async with CanSpindleSensor(interface="virtual", channel=channel, stale_after_s=2.0) as sensor:
                await sensor.connect()
                replay = Replay(csv_path, can_path, bus=bus, speed=20.0, port=0)
                async with replay:
                    readings = [await sensor.read() for _ in range(45)]
            assert all(isinstance(r, CanReading) for r in readings)
            assert sensor.metrics.events.get("frames_lost", 0) == 0
            return [r.speed_rpm for r in readings]
        finally:
            bus.shutdown()

    assert asyncio.run(main()) == [3000.0 + k for k in range(45)]


def test_a_logged_can_fd_frame_is_replayed_as_fd_and_rejected(tmp_path: Path) -> None:
    from drivers.errors import FrameError
    from drivers.logs import read_can_log
    from drivers.sim.replay import CanReplayer

    path = tmp_path / "fd.log"
    data = encode_status(3000, 5.0, 0, 0)
    write_can_log(path, [can.Message(timestamp=T0.timestamp(), arbitration_id=0x181, is_fd=True, data=data)])
    channel = f"replay-{uuid.uuid4().hex}"

    async def main() -> None:
        bus = can.Bus(interface="virtual", channel=channel, ignore_config=True)
        try:
            async with CanSpindleSensor(interface="virtual", channel=channel, stale_after_s=2.0) as sensor:
                await sensor.connect()
                replayer = CanReplayer(read_can_log(path), bus=bus)
                replayer.start()
                with pytest.raises(FrameError, match="CAN FD frame"):
                    await sensor.read()
                replayer.stop()
        finally:
            bus.shutdown()

    asyncio.run(main())
