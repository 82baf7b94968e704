"""Engine and session factory, built at the edge from ``settings.database`` (nothing opens at import).

SQLite gets WAL journaling (readers never block the writer thread), ``foreign_keys=ON`` and a busy timeout on
every new connection; its parent directory is created. PostgreSQL gets a connect timeout and pre-ping so a
restarted server is noticed on the next checkout instead of failing a write.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from sqlalchemy import Engine, create_engine, event
from sqlalchemy.engine import make_url
from sqlalchemy.orm import Session, sessionmaker

from service.db.errors import DatabaseUnavailableError


def create_db_engine(
    url: str,
    *,
    echo: bool = False,
    connect_timeout_s: float = 5.0,
    sqlite_busy_timeout_ms: int = 5000,
    create_dirs: bool = True,
) -> Engine:
    """An engine for ``url`` (``sqlite:///path`` or ``postgresql+psycopg://…``), configured as above."""
    parsed = make_url(url)
    if parsed.get_backend_name() == "sqlite":
        return _sqlite_engine(url, echo=echo, busy_timeout_ms=sqlite_busy_timeout_ms, create_dirs=create_dirs)
    connect_args: dict[str, Any] = {}
    if parsed.get_backend_name() == "postgresql":
        connect_args["connect_timeout"] = max(1, round(connect_timeout_s))
    return create_engine(url, echo=echo, pool_pre_ping=True, connect_args=connect_args)


def _sqlite_engine(url: str, *, echo: bool, busy_timeout_ms: int, create_dirs: bool) -> Engine:
    database = make_url(url).database
    in_memory = database in (None, "", ":memory:") or str(database).startswith("file::memory:")
    if create_dirs and not in_memory:
        parent = Path(str(database)).expanduser().parent
        try:
            parent.mkdir(parents=True, exist_ok=True)
        except OSError as err:
            raise DatabaseUnavailableError(f"cannot create the SQLite directory {parent}: {err}") from err
    engine = create_engine(url, echo=echo, connect_args={"timeout": busy_timeout_ms / 1000.0})

    @event.listens_for(engine, "connect")
    def _on_connect(dbapi_conn: Any, _record: Any) -> None:
        cursor = dbapi_conn.cursor()
        try:
            if not in_memory:
                cursor.execute("PRAGMA journal_mode=WAL")
            cursor.execute("PRAGMA foreign_keys=ON")
            cursor.execute(f"PRAGMA busy_timeout={int(busy_timeout_ms)}")
        finally:
            cursor.close()

    return engine


def make_session_factory(engine: Engine) -> sessionmaker[Session]:
    """Sessions that keep loaded attributes after commit (rows are handed to other threads read-only)."""
    return sessionmaker(engine, expire_on_commit=False)
