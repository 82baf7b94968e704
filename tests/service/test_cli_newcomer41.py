"""What a newcomer met (issue 41 section 5): each test failed before its fix."""

from __future__ import annotations

import socket
from pathlib import Path

import pytest
from sqlalchemy import text

from service.cli import main
from service.commands._common import check_database_url
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
    import service.engine.runtime as runtime
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
