"""What a newcomer met (issue 41 section 5): each test failed before its fix."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
from sqlalchemy import text

from service.cli import main
from service.commands._common import check_database_url
from service.contracts.mechanics import is_shipped_example
from service.store.dburl import normalize_database_url
from service.store.engine import create_db_engine


@pytest.mark.parametrize(
    "url", ["postgres://127.0.0.1:5432/test", "postgresql://127.0.0.1:5432/test", "POSTGRES://127.0.0.1/test"]
)
def test_the_common_postgresql_spellings_are_accepted(url: str) -> None:
    """Item 2: ``--database-url postgres://…`` was a 24-line ``NoSuchModuleError`` in ``run`` and ``demo``
    (``postgresql://`` asks for psycopg2, not installed)."""
    assert normalize_database_url(url).startswith("postgresql+psycopg://127.0.0.1")
    check_database_url(url, "--database-url")  # no CommandError: the store can use it
    engine = create_db_engine(url)
    try:
        assert engine.dialect.name == "postgresql" and engine.dialect.driver == "psycopg"
        with engine.connect() as conn:
            assert conn.execute(text("SELECT 1")).scalar() == 1
    finally:
        engine.dispose()


def test_other_urls_are_left_as_written() -> None:
    for url in ("sqlite:///x.db", "postgresql+psycopg://u@h/d", "mysql://a@b/c", "not a url"):
        assert normalize_database_url(url) == url


@pytest.fixture
def no_model_load(monkeypatch: pytest.MonkeyPatch) -> None:
    """A model load fails the test: the check under test must come before it."""
    import service.host.runtime as runtime
    import service.modelload as modelload

    def no_load(*a: object, **k: object) -> None:
        raise AssertionError("the model was loaded before the check")

    monkeypatch.setattr(runtime, "load_model", no_load)
    monkeypatch.setattr(modelload, "load_model", no_load)


@pytest.mark.parametrize("command", ["run", "demo"])
def test_a_busy_opcua_port_is_one_line_before_the_model_loads(
    command: str,
    tmp_path: Path,
    no_model_load: None,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Item 1: the OPC UA port in use was exit 1 and three tracebacks (106 lines) after the model had loaded;
    the REST port in use was already one line before loading."""
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen(1)
        port = busy.getsockname()[1]
        monkeypatch.setenv("CHTC_OPCUA__ENABLED", "true")
        monkeypatch.setenv("CHTC_OPCUA__PORT", str(port))
        monkeypatch.setenv("CHTC_DATABASE__URL", f"sqlite:///{tmp_path / 'x.db'}")
        with socket.socket() as free:  # the REST port: free (``run`` takes no port 0)
            free.bind(("127.0.0.1", 0))
            rest = free.getsockname()[1]
        argv = [command, "--port", str(rest)] + (["--duration", "0"] if command == "demo" else [])
        assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"chtc {command}: opcua.port: cannot listen on 127.0.0.1:{port}"), err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1


DATA = Path(__file__).resolve().parents[2] / "service" / "data"


@pytest.mark.slow
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_replay_stops_within_seconds_on_sigint_and_sigterm(sig: int, tmp_path: Path) -> None:
    """Item 15: ``chtc replay`` did not stop on SIGINT within 20 s (4 of 4 tries) or 120 s; SIGTERM was as
    abrupt as kill -9. Now either stops it within a few seconds, writes what was identified and exits 130
    (about 40 s: the model comes from the ROM cache)."""
    out, log = tmp_path / "ids.json", tmp_path / "out.txt"
    argv = [sys.executable, "-m", "service.cli", "replay", str(DATA / "example_temperatures.csv")]
    argv += [str(DATA / "example_can.blf"), "--database-url", f"sqlite:///{tmp_path / 'r.db'}"]
    argv += ["--out", str(out), "--speedup", "10"]
    with log.open("w") as fo:
        proc = subprocess.Popen(argv, stdout=fo, stderr=subprocess.STDOUT, start_new_session=True)
        try:
            deadline = time.monotonic() + 240.0
            while "condition 1:" not in log.read_text() and time.monotonic() < deadline:
                assert proc.poll() is None, log.read_text()
                time.sleep(0.5)
            started = time.monotonic()
            os.killpg(proc.pid, sig)
            code = proc.wait(timeout=30)
            took = time.monotonic() - started
        finally:
            if proc.poll() is None:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()
    text_out = log.read_text()
    assert code == 130 and took < 15.0, (code, took, text_out[-2000:])
    assert "replay interrupted" in text_out and "Traceback" not in text_out, text_out[-2000:]
    assert out.exists()


def _disp(rows: list[tuple[str, float]], time_col: str = "time") -> str:
    return f"{time_col},axial_um\n" + "".join(f"{t},{a}\n" for t, a in rows)


def test_a_displacement_file_in_mm_gets_the_unit_hint() -> None:
    """Item 8: a file in mm (a 4-µm growth written 0.004) was fitted and got ``drift … the fixture slipped``,
    not the unit hint the docs promise."""
    from service.shell.commissioning import DisplacementFormatError, parse_displacement_csv

    rows = [(f"2026-11-27T06:{m:02d}:00Z", 0.004 * m / 59) for m in range(60)]
    with pytest.raises(DisplacementFormatError, match=r"in mm\? The file's unit is µm"):
        parse_displacement_csv(_disp(rows), "d.csv")
    ok = parse_displacement_csv(_disp([(t, 1000 * a) for t, a in rows], "timestamp_utc"), "d.csv")
    assert ok.axial_um.size == 60  # in µm, with the temperature CSV's time column name: accepted


def test_swapped_test_files_say_the_order(capsys: pytest.CaptureFixture[str]) -> None:
    """Item 8: swapped files listed the CSV's columns instead of saying the order is wrong."""
    temps = DATA / "example_thermal_test_temperatures.csv"
    can = DATA / "example_thermal_test_can.blf"
    disp = DATA / "example_thermal_test_displacements.csv"
    for argv in ([disp, can, temps], [temps, can, temps]):
        assert main(["commission", "growth", *map(str, argv)]) == 2
        err = capsys.readouterr().err
        assert "the order is TEMPERATURES CAN DISPLACEMENTS" in err, err
        assert len(err.strip().splitlines()) == 1, err


def test_the_shipped_example_thermal_test_is_refused_by_a_running_service() -> None:
    """Item 7: the shipped example thermal test was accepted by any running service, which then ended
    "usable" with another machine's mechanics. It is marked; refused (409) outside the demo unless forced."""
    import base64

    from fastapi.testclient import TestClient

    from api.app import create_app
    from api.deps import ClockInfo
    from service.settings import Settings

    disp = (DATA / "example_thermal_test_displacements.csv").read_text(encoding="utf-8")
    assert is_shipped_example(disp)
    token = "w" * 32
    body = {
        "temperatures_csv": (DATA / "example_thermal_test_temperatures.csv").read_text(encoding="utf-8"),
        "can_log_base64": base64.b64encode((DATA / "example_thermal_test_can.blf").read_bytes()).decode(),
        "can_log_format": "blf",
        "displacements_csv": disp,
    }
    app = create_app(Settings(api={"token": token}), None, clock_info=ClockInfo())  # type: ignore[arg-type]
    with TestClient(app) as client:
        r = client.post(
            "/api/v1/compensation/mechanics", json=body, headers={"Authorization": f"Bearer {token}"}
        )
    assert r.status_code == 409, r.text
    assert "shipped example" in r.json()["error"]["message"]
