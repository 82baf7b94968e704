"""Temperature CSV and CAN log: write -> read round trips; corrupt or truncated files name the line/frame."""

from __future__ import annotations

import math
from datetime import UTC, datetime, timedelta
from pathlib import Path

import can
import numpy as np
import pytest

from drivers.logs import (
    LogFormatError,
    TemperatureCsvWriter,
    csv_header,
    read_can_log,
    read_temperature_csv,
    write_can_log,
)

T0 = datetime(2026, 1, 2, 3, 4, 5, 123456, tzinfo=UTC)


def _write_csv(path: Path, n: int = 5) -> np.ndarray:
    rng = np.random.default_rng(1)
    temps = 20.0 + rng.random((n, 32)) * 10.0
    temps[2, 7] = math.nan
    with TemperatureCsvWriter(path) as w:
        for i in range(n):
            status = np.zeros(32, dtype=int)
            status[i % 32] = 1 + i % 2
            w.write(T0 + timedelta(seconds=i), temps_c=temps[i], ambient_c=21.0 + i, status=status, counter=i)
    return temps


def test_csv_round_trip(tmp_path: Path) -> None:
    path = tmp_path / "t.csv"
    temps = _write_csv(path)
    assert path.read_text().splitlines()[0] == ",".join(csv_header(32))
    log = read_temperature_csv(path)
    np.testing.assert_array_equal(log.temps_c, temps)  # NaN in the same place, exact floats
    assert log.timestamps()[3] == T0 + timedelta(seconds=3)
    assert list(log.counter) == [0, 1, 2, 3, 4]
    assert list(log.ambient_c) == [21.0, 22.0, 23.0, 24.0, 25.0]
    assert log.status[1, 1] == 2 and log.status[0, 0] == 1 and log.status.sum() == 1 + 2 + 1 + 2 + 1


def _corrupt(path: Path, line: int, fn: object) -> None:
    lines = path.read_text().splitlines(keepends=True)
    lines[line - 1] = fn(lines[line - 1])  # type: ignore[operator]
    path.write_text("".join(lines))


@pytest.mark.parametrize(
    ("line", "edit", "message"),
    [
        (1, lambda s: s.replace("ch05_c", "ch5"), "header column 8"),
        (3, lambda s: s.replace("+00:00", "", 1), "no UTC offset"),
        (4, lambda s: "x" + s, "timestamp_utc"),
        (5, lambda s: s.rsplit(",", 3)[0] + "\n", "expected 67 fields"),
        (5, lambda s: s.replace(",0,", ",7,", 1), "status must be 0, 1 or 2"),
        (6, lambda s: s.replace(",", ",abc", 3), "not a number"),
        (3, lambda s: s.replace("2026-01-02T03:04:06", "2026-01-02T03:04:04"), "backwards"),
    ],
)
def test_corrupt_csv_names_the_line(tmp_path: Path, line: int, edit: object, message: str) -> None:
    path = tmp_path / "t.csv"
    _write_csv(path)
    _corrupt(path, line, edit)
    with pytest.raises(LogFormatError, match=message) as info:
        read_temperature_csv(path)
    assert info.value.line == line and str(path) in str(info.value)


def test_truncated_csv_names_the_last_line(tmp_path: Path) -> None:
    path = tmp_path / "t.csv"
    _write_csv(path)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) - 40])
    with pytest.raises(LogFormatError, match="line 6") as info:
        read_temperature_csv(path)
    assert info.value.line == 6


def _frames(n: int = 50) -> list[can.Message]:
    t = T0.timestamp()
    return [
        can.Message(
            timestamp=t + 0.01 * i,
            arbitration_id=0x181,
            is_extended_id=False,
            data=bytes([i % 256, 0, 1, 2, i % 16, 0]),
        )
        for i in range(n)
    ]


ALL_SUFFIXES = [".asc", ".blf", ".log", ".csv", ".trc", ".mf4"]


@pytest.mark.parametrize("suffix", ALL_SUFFIXES)
def test_can_log_round_trip(tmp_path: Path, suffix: str) -> None:
    path = tmp_path / f"can{suffix}"
    frames = _frames()
    assert write_can_log(path, frames) == 50
    back = read_can_log(path)
    assert [m.data for m in back] == [m.data for m in frames]
    assert [m.arbitration_id for m in back] == [0x181] * 50
    tol = 1e-3 if suffix == ".asc" else 1e-5  # ASC keeps the start time to the millisecond
    np.testing.assert_allclose([m.timestamp for m in back], [m.timestamp for m in frames], atol=tol, rtol=0)


@pytest.mark.parametrize("suffix", ALL_SUFFIXES)
def test_truncated_can_log_names_the_frame(tmp_path: Path, suffix: str) -> None:
    path = tmp_path / f"can{suffix}"
    write_can_log(path, _frames(400))
    data = path.read_bytes()
    path.write_bytes(data[: len(data) * 2 // 3 + 3])
    with pytest.raises(LogFormatError, match=r"frame \d+") as info:
        read_can_log(path)
    # an MF4 file is read as a whole: cut short, it cannot be opened at all (frame 1)
    low = 0 if suffix == ".mf4" else 1
    assert info.value.frame is not None and low < info.value.frame <= 400


@pytest.mark.parametrize("suffix", [".asc", ".log", ".csv", ".trc"])
def test_corrupt_can_log_names_the_frame(tmp_path: Path, suffix: str) -> None:
    path = tmp_path / f"can{suffix}"
    write_can_log(path, _frames(20))
    lines = path.read_text().splitlines(keepends=True)
    frame_lines = [i for i, s in enumerate(lines) if "181" in s and "Begin" not in s]
    lines[frame_lines[10]] = "garbage !!\n"
    path.write_text("".join(lines))
    with pytest.raises(LogFormatError) as info:
        read_can_log(path)
    assert info.value.frame == 11


def test_invalid_frame_in_a_log_is_named(tmp_path: Path) -> None:
    path = tmp_path / "can.log"
    frames = _frames(5)
    frames[3].timestamp -= 1.0
    write_can_log(path, frames)
    with pytest.raises(LogFormatError, match="frame 4: timestamp goes backwards"):
        read_can_log(path)


def test_unsupported_suffix(tmp_path: Path) -> None:
    with pytest.raises(LogFormatError, match="unsupported"):
        read_can_log(tmp_path / "x.mdf")


@pytest.mark.parametrize("suffix", ALL_SUFFIXES)
def test_any_channel_name_can_be_logged(tmp_path: Path, suffix: str) -> None:
    frames = _frames(3)
    for m, name in zip(frames, ["sim-deadbeef99999999", "ws://127.0.0.1:54701/", 2], strict=True):
        m.channel = name
    write_can_log(tmp_path / f"c{suffix}", frames)
    assert [m.data for m in read_can_log(tmp_path / f"c{suffix}")] == [m.data for m in frames]
