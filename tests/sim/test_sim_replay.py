"""Replay building blocks: CSV rows as a timeline aligned with the CAN log; bad logs refused up front."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta
from pathlib import Path

import can
import numpy as np
import pytest

from drivers.logs import LogFormatError, TemperatureCsvWriter, read_temperature_csv, write_can_log
from drivers.sim.replay import Replay, timeline_from_log
from drivers.sim.source import TimelineSource
from tests.sim.simhelpers import FakeClock

T0 = datetime(2026, 3, 1, 12, 0, tzinfo=UTC)


def _csv(path: Path, n: int = 4, start: datetime = T0) -> None:
    with TemperatureCsvWriter(path) as w:
        for i in range(n):
            w.write(
                start + timedelta(seconds=i), temps_c=np.full(32, 20.0 + i), ambient_c=21.0, counter=50 + i
            )


def _can(path: Path, n: int = 30, start: datetime = T0) -> None:
    frames = [
        can.Message(
            timestamp=start.timestamp() + 0.1 * i, arbitration_id=0x181, is_extended_id=False, data=bytes(6)
        )
        for i in range(n)
    ]
    write_can_log(path, frames)


def test_timeline_from_log_aligns_to_an_earlier_reference(tmp_path: Path) -> None:
    _csv(tmp_path / "t.csv")
    log = read_temperature_csv(tmp_path / "t.csv")
    timeline, counters = timeline_from_log(log, t_ref=log.t_s[0] - 2.0)
    assert list(timeline.times_s) == [0.0, 2.0, 3.0, 4.0, 5.0]
    assert counters == [50, 50, 51, 52, 53]
    src = TimelineSource(timeline, mode="hold", clock=FakeClock())
    assert src.at(0.5).temps_c[0] == 20.0 and src.at(3.999).temps_c[0] == 21.0


def test_replay_reference_is_the_earlier_log_start(tmp_path: Path) -> None:
    _csv(tmp_path / "t.csv", start=T0 + timedelta(seconds=1))
    _can(tmp_path / "c.blf")
    replay = Replay(tmp_path / "t.csv", tmp_path / "c.blf", bus=None, speed=2.0, port=0)
    assert replay.t_ref == T0.timestamp()
    assert replay.duration_s == pytest.approx(4.0 / 2.0)  # last CSV row at T0 + 4 s, at 2x


def test_replay_refuses_a_truncated_can_log_naming_the_frame(tmp_path: Path) -> None:
    _csv(tmp_path / "t.csv")
    _can(tmp_path / "c.blf", n=400)
    data = (tmp_path / "c.blf").read_bytes()
    (tmp_path / "c.blf").write_bytes(data[: len(data) // 2])
    with pytest.raises(LogFormatError, match=r"c\.blf, frame \d+: truncated"):
        Replay(tmp_path / "t.csv", tmp_path / "c.blf", bus=None, port=0)


def test_replay_refuses_a_corrupt_csv_naming_the_line(tmp_path: Path) -> None:
    _csv(tmp_path / "t.csv")
    text = (tmp_path / "t.csv").read_text().splitlines(keepends=True)
    text[3] = text[3].replace("20", "2O", 1)
    (tmp_path / "t.csv").write_text("".join(text))
    with pytest.raises(LogFormatError, match=r"t\.csv, line 4: "):
        Replay(tmp_path / "t.csv", None, bus=None, port=0)
