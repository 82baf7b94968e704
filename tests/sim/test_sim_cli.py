"""``chtc simulate`` and ``chtc record`` as separate processes (slow), and the profile loader."""

from __future__ import annotations

import json
import socket
import subprocess
import sys
import time
from datetime import UTC, datetime, timedelta
from pathlib import Path

import can
import numpy as np
import pytest

from drivers.logs import TemperatureCsvWriter, read_can_log, read_temperature_csv, write_can_log
from service.commands.simulate import ProfileError, load_profile


def test_named_and_file_profiles(tmp_path: Path) -> None:
    assert [s.speed_rpm for s in load_profile("steps")] == [3000.0, 4000.0, 5000.0]
    toml = tmp_path / "p.toml"
    toml.write_text("[[segment]]\nduration_s = 60\nspeed_rpm = 3000\ntorque_nm = 5\nambient_c = 22\n")
    assert load_profile(str(toml))[0].duration_s == 60.0
    bad = tmp_path / "p.json"
    bad.write_text(json.dumps([{"duration_s": 60, "speed_rpm": "fast", "torque_nm": 1, "ambient_c": 20}]))
    with pytest.raises(ProfileError, match=r"segment\[0\]\.speed_rpm"):
        load_profile(str(bad))
    with pytest.raises(ProfileError, match="not a named profile"):
        load_profile("nonsense")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _wait_for_line(proc: subprocess.Popen[str], text: str, timeout: float = 60.0) -> list[str]:
    lines: list[str] = []
    deadline = time.monotonic() + timeout
    assert proc.stdout is not None
    while time.monotonic() < deadline:
        line = proc.stdout.readline()
        if not line:
            break
        lines.append(line)
        if text in line:
            return lines
    raise AssertionError(f"{text!r} not printed; got {lines}")


def _recording(tmp_path: Path, seconds: float = 3.0) -> tuple[Path, Path]:
    t0 = datetime.now(UTC) - timedelta(hours=1)
    csv_path, can_path = tmp_path / "in.csv", tmp_path / "in.log"
    with TemperatureCsvWriter(csv_path) as w:
        for i in range(int(seconds / 0.25)):
            w.write(
                t0 + timedelta(seconds=0.25 * i),
                temps_c=np.full(32, 30.0 + i),
                ambient_c=21.0,
                counter=100 + i,
            )
    frames = [
        can.Message(
            timestamp=t0.timestamp() + 0.01 * i,
            arbitration_id=0x181,
            is_extended_id=False,
            data=bytes([0xB8, 0x0B, 0xF4, 0x01, i % 16, 0]),
        )
        for i in range(int(seconds / 0.01))
    ]
    write_can_log(can_path, frames)
    return csv_path, can_path


@pytest.mark.slow
def test_simulate_replay_process_recorded_by_record_process(tmp_path: Path) -> None:
    csv_path, can_path = _recording(tmp_path)
    port, hub = _free_port(), _free_port()
    sim = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "service.cli",
            "simulate",
            "--replay-csv",
            str(csv_path),
            "--replay-can",
            str(can_path),
            "--modbus-port",
            str(port),
            "--can-channel",
            f"ws://127.0.0.1:{hub}/",
            "--duration",
            "30",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    try:
        lines = _wait_for_line(sim, "Ctrl-C to stop")
        assert any(f"127.0.0.1:{port}" in line for line in lines)
        assert any(f"ws://127.0.0.1:{hub}/" in line for line in lines)
        out = tmp_path / "rec"
        rec = subprocess.run(
            [
                sys.executable,
                "-m",
                "service.cli",
                "record",
                "--out",
                str(out),
                "--modbus-port",
                str(port),
                "--can-channel",
                f"ws://127.0.0.1:{hub}/",
                "--duration",
                "2",
                "--interval",
                "0.1",
                "--can-format",
                "asc",
            ],
            capture_output=True,
            text=True,
            timeout=60,
        )
        assert rec.returncode == 0, rec.stdout + rec.stderr
        assert "done:" in rec.stdout
    finally:
        sim.terminate()
        sim.wait(10)
    log = read_temperature_csv(out / "temperatures.csv")
    assert log.n_rows >= 3
    assert set(log.counter) <= set(range(100, 112))
    np.testing.assert_array_equal(log.temps_c[:, 0], log.counter - 70.0)  # row i: 30 + i °C, counter 100 + i
    frames = read_can_log(out / "can.asc")
    assert len(frames) >= 50
    assert {bytes(m.data[:4]) for m in frames} == {bytes([0xB8, 0x0B, 0xF4, 0x01])}


@pytest.mark.slow
def test_simulate_plant_prints_what_it_serves_and_stops_after_duration(tmp_path: Path) -> None:
    profile = tmp_path / "p.json"
    profile.write_text(json.dumps([{"duration_s": 60, "speed_rpm": 3000, "torque_nm": 5, "ambient_c": 22}]))
    run = subprocess.run(
        [
            sys.executable,
            "-m",
            "service.cli",
            "simulate",
            "--profile",
            str(profile),
            "--modbus-port",
            "0",
            "--can-channel",
            "ws://127.0.0.1:0/",
            "--duration",
            "1",
            "--speedup",
            "60",
            "--fault",
            "open:ch=3,at=0.5",
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert run.returncode == 0, run.stdout + run.stderr
    assert "Modbus TCP DAQ on 127.0.0.1:" in run.stdout
    assert "python-can-remote hub ws://127.0.0.1:" in run.stdout
    assert "fault: open ch=3 from 0.5 s until cleared" in run.stdout


def test_simulate_rejects_a_bad_fault() -> None:
    run = subprocess.run(
        [
            sys.executable,
            "-m",
            "service.cli",
            "simulate",
            "--fault",
            "melt:ch=1",
            "--no-can",
            "--duration",
            "0",
        ],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert run.returncode == 1
    assert "fault kind 'melt' unknown" in run.stderr


@pytest.mark.slow
def test_record_of_a_sped_up_simulation_stamps_the_simulated_time(tmp_path: Path) -> None:
    """``chtc record --speedup S`` against ``chtc simulate --speedup S``: rows and frames in plant time
    (before, both were stamped with wall time, so 3 s of recording covered 3 s instead of 3 x 30 s)."""
    profile = tmp_path / "p.json"
    profile.write_text(json.dumps([{"duration_s": 600, "speed_rpm": 3000, "torque_nm": 5, "ambient_c": 22}]))
    port, hub = _free_port(), _free_port()
    where = ["--modbus-port", str(port), "--can-channel", f"ws://127.0.0.1:{hub}/"]
    cli = [sys.executable, "-m", "service.cli"]
    sim = subprocess.Popen(
        [*cli, "simulate", "--profile", str(profile), "--speedup", "30", *where, "--duration", "60"],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    try:
        _wait_for_line(sim, "Ctrl-C to stop")
        out = tmp_path / "rec"
        rec = subprocess.run(
            [
                *cli,
                "record",
                "--out",
                str(out),
                "--speedup",
                "30",
                *where,
                "--duration",
                "3",
                "--interval",
                "0.05",
                "--can-format",
                "asc",
            ],
            capture_output=True,
            text=True,
            timeout=60,
        )
        assert rec.returncode == 0, rec.stdout + rec.stderr
    finally:
        sim.terminate()
        sim.wait(10)
    log = read_temperature_csv(out / "temperatures.csv")
    span = float(log.t_s[-1] - log.t_s[0])
    assert 60.0 <= span <= 95.0, span  # ~3 s wall x 30, less the first and last poll
    frames = read_can_log(out / "can.asc")
    frame_span = frames[-1].timestamp - frames[0].timestamp
    assert 60.0 <= frame_span <= 95.0, frame_span
    assert abs(frames[0].timestamp - float(log.t_s[0])) < 10.0  # one time base for both files
