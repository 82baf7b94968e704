"""What a newcomer met on the command line (issue 25, section 2): each test failed before its fix."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from service.cli import main


@pytest.fixture
def no_model_load(monkeypatch: pytest.MonkeyPatch) -> None:
    """A model load fails the test: the check under test must come before it (about 10-46 s). Patched where
    the commands call it (``Runtime.load``), with the runtime imported first: imported under the patch, it
    kept the failing stand-in for the later tests of this module."""
    import service.host.runtime as runtime
    import service.modelload as modelload

    def no_load(*a: object, **k: object) -> None:
        raise AssertionError("the model was loaded before the database URL was checked")

    monkeypatch.setattr(runtime, "load_model", no_load)
    monkeypatch.setattr(modelload, "load_model", no_load)


@pytest.mark.parametrize(
    ("url", "expected"),
    [
        ("mysql://a@b/c", "database 'mysql' is not supported"),
        ("postgresql+asyncpg://u@127.0.0.1/x", "driver 'asyncpg' is not supported for postgresql"),
        ("sqlite:////proc/no/such/dir/x.db", "cannot create the SQLite directory /proc/no/such/dir"),
    ],
)
def test_demo_unusable_database_url_is_one_line_before_the_model_loads(
    url: str, expected: str, no_model_load: None, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["demo", "--database-url", url, "--port", "0", "--duration", "0"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("chtc demo: --database-url: ") and expected in err, err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1


def test_run_names_the_settings_key_of_an_unusable_url(
    no_model_load: None, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("CHTC_DATABASE__URL", "mysql://a@b/c")
    assert main(["run"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("chtc run: database.url: database 'mysql' is not supported"), err


DATA = Path(__file__).resolve().parents[2] / "service" / "data"
TEMPS, CAN = DATA / "example_temperatures.csv", DATA / "example_can.blf"


@pytest.mark.parametrize("command", ["identify", "replay"])
def test_swapped_logs_name_the_argument(
    command: str, tmp_path: Path, no_model_load: None, capsys: pytest.CaptureFixture[str]
) -> None:
    """``chtc identify can.blf temps.csv`` said ``'utf-8' codec can't decode byte 0x90``."""
    binary_csv = tmp_path / "can.csv"  # a CAN log under a CSV name: caught by its content
    binary_csv.write_bytes(CAN.read_bytes())
    cases = [
        ([str(CAN), str(TEMPS)], "argument CSV: ", "is not a temperature CSV but a CAN log (.blf)"),
        ([str(binary_csv), str(TEMPS)], "argument CSV: ", "is not a temperature CSV (binary content"),
        ([str(TEMPS), str(TEMPS)], "argument CAN: ", "is not a CAN log but a temperature CSV"),
    ]
    for argv, where, what in cases:
        assert main([command, *argv]) == 2
        err = capsys.readouterr().err
        assert err.startswith(f"chtc {command}: {where}") and what in err, err
        assert "codec" not in err and "Traceback" not in err and len(err.strip().splitlines()) == 1


@pytest.mark.slow
def test_demo_starts_without_a_connect_warning_and_stops_quietly_on_ctrl_c(tmp_path: Path) -> None:
    """``chtc demo`` logged ``DeviceUnavailableError ... cannot connect`` at every start (the drivers polled
    before the simulated DAQ listened), and Ctrl-C printed the worker process' ``KeyboardInterrupt``
    traceback. A terminal's Ctrl-C reaches the whole process group: so does the SIGINT here (about 60 s)."""
    import sys

    from benchmarks.api_live import rig_pids

    argv = [sys.executable, "-m", "service.cli", "demo", "--port", "0", "--quiet", "--segment-min", "5"]
    argv += ["--database-url", f"sqlite:///{tmp_path / 'demo.db'}"]
    out, err = tmp_path / "out.txt", tmp_path / "err.txt"
    with out.open("w") as fo, err.open("w") as fe, _process_group(argv, stdout=fo, stderr=fe) as proc:
        deadline = time.monotonic() + 240.0
        while "plant profile" not in out.read_text() and time.monotonic() < deadline:
            assert proc.poll() is None, err.read_text()
            time.sleep(0.5)
        assert "plant profile" in out.read_text(), "the demo did not start within 240 s"
        # the simulated devices and the plant run in a child process of their own (issue 30)
        rigs = rig_pids(proc.pid)
        assert len(rigs) == 1, rigs
        # the acquisition polls the devices; the worker process waits for jobs
        code = _ctrl_c(proc, settle_s=5.0)
    assert not Path(f"/proc/{rigs[0]}").exists(), "the rig process outlived the demo (the demo reaps it)"
    stderr = err.read_text()
    assert "Traceback" not in stderr and "KeyboardInterrupt" not in stderr, stderr
    assert "cannot connect" not in stderr and "DeviceUnavailableError" not in stderr, stderr
    assert code == 0 and "demo stopped" in out.read_text()


@contextlib.contextmanager
def _process_group(argv: list[str], **popen: Any) -> Iterator[subprocess.Popen[bytes]]:
    """A command in a process group of its own (as a terminal runs it), killed if a test leaves it running."""
    proc = subprocess.Popen(argv, start_new_session=True, **popen)
    try:
        yield proc
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()


def _ctrl_c(proc: subprocess.Popen[bytes], *, settle_s: float) -> int:
    """After ``settle_s``, Ctrl-C as a terminal sends it (SIGINT to the process group): the exit code."""
    time.sleep(settle_s)
    os.killpg(proc.pid, signal.SIGINT)
    return proc.wait(timeout=60)


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.mark.slow
def test_run_creates_a_fresh_sqlite_schema_and_stops_quietly_on_ctrl_c(tmp_path: Path) -> None:
    """``chtc run`` on a new SQLite file used to need ``--migrate`` first (db ``down``: no chtc schema);
    Ctrl-C printed the worker process' traceback (about 30 s: the model comes from the ROM cache)."""
    import json
    import sys
    import urllib.request

    api_port = _free_port()
    env = os.environ | {
        "CHTC_DATABASE__URL": f"sqlite:///{tmp_path / 'new' / 'chtc.db'}",
        "CHTC_API__PORT": str(api_port),
        "CHTC_MODBUS__PORT": str(_free_port()),  # no DAQ: reported, not fatal
        "CHTC_CAN__CHANNEL": f"chtc-test-{os.getpid()}",
    }
    err = tmp_path / "err.txt"
    db: dict[str, object] = {}
    with err.open("w") as fe:
        argv = [sys.executable, "-m", "service.cli", "run"]
        with _process_group(argv, env=env, stdout=subprocess.DEVNULL, stderr=fe) as proc:
            deadline = time.monotonic() + 180.0
            while db.get("status") != "ok" and time.monotonic() < deadline:
                assert proc.poll() is None, err.read_text()
                time.sleep(0.5)
                try:
                    url = f"http://127.0.0.1:{api_port}/api/v1/healthz"
                    with urllib.request.urlopen(url, timeout=2) as r:
                        devices = json.load(r)["devices"]
                except OSError:
                    continue
                db = next(d for d in devices if d["name"] == "db")
            code = _ctrl_c(proc, settle_s=2.0)  # the worker process waits for jobs
    stderr = err.read_text()
    assert db.get("status") == "ok", (db, stderr)
    assert "no chtc schema" not in stderr
    assert "Traceback" not in stderr and "KeyboardInterrupt" not in stderr, stderr
    assert code == 0


def _record(rid: int, identified: list[bool], method: str, outcome: str = "ok") -> object:
    from datetime import UTC, datetime
    from types import SimpleNamespace

    t = datetime(2026, 3, 2, 6, 0, tzinfo=UTC)
    return SimpleNamespace(
        id=rid,
        outcome=outcome,
        message="",
        method=method,
        condition=SimpleNamespace(id=2, speed_rpm=3000.0, ambient_c=22.0),
        window_from=t,
        window_to=t,
        h=[50.0] * 7,
        ci95_lo=[1.0] * 7,
        ci95_hi=[2500.0] * 7,
        identified=identified,
        fit=0.98,
        rmse_c=0.15,
    )


def test_identify_lines_say_how_many_h_are_identified_and_which_fit_it_is() -> None:
    """Every line said ``ok``, also when all seven H were poorly identified, and did not tell a speed-map fit
    from a per-condition fit."""
    from service.commands.identify import format_record, summary_line

    weak = _record(1, [False] * 7, "speed-map")
    partial = _record(2, [True, True, True] + [False] * 4, "hybrid")
    full = _record(3, [True] * 7, "hybrid")
    heads = [format_record(r).splitlines()[0] for r in (weak, partial, full)]  # type: ignore[arg-type]
    assert heads[0].startswith("#1 weak 0/7 H") and "speed-map fit" in heads[0]
    assert heads[1].startswith("#2 partial 3/7 H") and "per-condition fit" in heads[1]
    assert heads[2].startswith("#3 ok 7/7 H") and "per-condition fit" in heads[2]
    summary = summary_line([weak, partial, full])  # type: ignore[list-item]
    assert summary == (
        "3 identifications: 1 ok (7/7 H), 1 partial, 1 weak; 1 speed-map fits, 2 per-condition fits"
    )


def _example_head(minutes: float, into: Path) -> tuple[Path, Path]:
    """The example recording's first ``minutes`` (temperature rows and CAN frames before then), written
    under ``into``."""
    from datetime import datetime

    from drivers.logs import read_can_log, write_can_log

    header, *rows = TEMPS.read_text(encoding="utf-8").splitlines(keepends=True)
    end = datetime.fromisoformat(rows[0].split(",", 1)[0]).timestamp() + 60.0 * minutes
    into.mkdir()
    temps, can_log = into / TEMPS.name, into / CAN.name
    temps.write_text(
        header + "".join(r for r in rows if datetime.fromisoformat(r.split(",", 1)[0]).timestamp() < end),
        encoding="utf-8",
    )
    write_can_log(can_log, [m for m in read_can_log(CAN) if m.timestamp < end])
    return temps, can_log


@pytest.mark.slow
def test_replay_prints_h_with_cis_and_writes_no_undocumented_file(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """``chtc replay`` printed no CIs and no ``?``, its speed-map lines no H at all, and wrote
    ``identifications_growth.json`` into the working directory. The example's first 23 min at 120x (about
    20 s): ``chtc identify`` finds a speed-map fit at 11 min, a per-condition one at 12 min and a second map
    fit at 21 min there (the whole 55-min example took about 35 s alone, 60 s in the full suite)."""
    import json

    temps, can_log = _example_head(23.0, tmp_path / "logs")
    work = tmp_path / "cwd"
    work.mkdir()
    monkeypatch.chdir(work)
    out = tmp_path / "out" / "ids.json"
    out.parent.mkdir()
    argv = ["replay", str(temps), str(can_log), "--speedup", "120", "--out", str(out)]
    assert main([*argv, "--database-url", f"sqlite:///{tmp_path / 'replay.db'}"]) == 0
    printed = capsys.readouterr().out
    rows = json.loads(out.read_text())
    ok = [r for r in rows if r["outcome"] == "ok"]
    maps = [r for r in ok if r["method"] == "speed-map"]
    assert ok and maps  # the default (combined) mode fits the speed map too
    blocks = [b for b in printed.split("\n#")[1:] if "W/(m²·K), 95 % CI ('?' = poorly identified" in b]
    assert len(blocks) == len(ok)
    # each block's first line names its fit (the summary line after the last block names both kinds)
    assert sum("speed-map fit" in b.splitlines()[0] for b in blocks) == len(maps)
    assert all(f"H{i}=" in b for b in blocks for i in range(1, 8))
    # the CIs as chtc identify prints them: a bound beyond the search box [5, 200] is "> 200" / "< 5"
    # (replay printed [4.63, 415] where identify printed [< 5, > 200]: issue 41 item 9)
    import re

    cis = [ci.split(", ") for b in blocks for ci in re.findall(r"H\d=[0-9.]+ \[([^\]]+)\]", b)]
    assert len(cis) == 7 * len(blocks)
    bounds = [float(x) for ci in cis for x in ci if not x.startswith(("<", ">"))]
    assert all(5.0 <= x <= 200.0 for x in bounds), sorted(bounds)[-3:]
    assert f"{len(rows)} identifications: " in printed
    assert list(work.iterdir()) == [] and sorted(p.name for p in out.parent.iterdir()) == ["ids.json"]
