"""Migrations: upgrade from empty, models == migration (autogenerate diff empty), downgrade, pragmas."""

from __future__ import annotations

from pathlib import Path

import pytest
import sqlalchemy as sa
from alembic import command
from alembic.autogenerate import compare_metadata
from alembic.config import Config
from alembic.migration import MigrationContext

from service.store import migrate
from service.store.engine import create_db_engine
from service.store.errors import DatabaseUnavailableError
from service.store.models import Base
from tests.db.tcp_proxy import free_port

TABLES = {
    "conditions",
    "identifications",
    "device_events",
    "samples",
    "offset_calibrations",
    "compensation_references",
    "live_state",
    "mechanics_calibrations",
    "probe_measurements",
}


def test_upgrade_from_empty_reaches_head_and_matches_models(db_url: str) -> None:
    eng = create_db_engine(db_url)
    try:
        assert migrate.current_revision(eng) is None
        migrate.upgrade(eng)
        assert migrate.current_revision(eng) == migrate.head_revision()
        with eng.connect() as conn:
            assert set(sa.inspect(conn).get_table_names()) >= TABLES
            ctx = MigrationContext.configure(
                conn, opts={"compare_type": True, "compare_server_default": True}
            )
            assert compare_metadata(ctx, Base.metadata) == []
    finally:
        eng.dispose()


def test_downgrade_to_base_and_upgrade_again(db_url: str) -> None:
    migrate.upgrade(db_url)
    migrate.downgrade(db_url, "base")
    eng = create_db_engine(db_url)
    try:
        with eng.connect() as conn:
            assert not TABLES & set(sa.inspect(conn).get_table_names())
        migrate.upgrade(eng)
        migrate.upgrade(eng)  # idempotent at head
        assert migrate.current_revision(eng) == migrate.head_revision()
    finally:
        eng.dispose()


def test_alembic_cli_config_uses_env_url(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    url = f"sqlite:///{tmp_path}/cli.db"
    monkeypatch.setenv("CHTC_DATABASE__URL", url)
    ini = Path(migrate.__file__).resolve().parent.parent / "alembic.ini"
    command.upgrade(Config(str(ini)), "head")
    assert migrate.current_revision(url) == migrate.head_revision()


def test_sqlite_connections_use_wal_foreign_keys_and_busy_timeout(tmp_path: Path) -> None:
    eng = create_db_engine(f"sqlite:///{tmp_path}/sub/dir/x.db", sqlite_busy_timeout_ms=1234)
    try:
        with eng.connect() as conn:
            assert conn.exec_driver_sql("PRAGMA journal_mode").scalar() == "wal"
            assert conn.exec_driver_sql("PRAGMA foreign_keys").scalar() == 1
            assert conn.exec_driver_sql("PRAGMA busy_timeout").scalar() == 1234
        assert (tmp_path / "sub" / "dir" / "x.db").exists()
    finally:
        eng.dispose()


def test_unreachable_database_is_a_typed_error(tmp_path: Path) -> None:
    closed = f"postgresql+psycopg://postgres@127.0.0.1:{free_port()}/test"
    with pytest.raises(DatabaseUnavailableError, match="migrate to head: database unavailable"):
        migrate.upgrade(closed)
    with pytest.raises(DatabaseUnavailableError, match="read schema revision"):
        migrate.current_revision(closed)
    (tmp_path / "file").write_text("")
    with pytest.raises(DatabaseUnavailableError, match="file"):
        create_db_engine(f"sqlite:///{tmp_path}/file/x.db")
