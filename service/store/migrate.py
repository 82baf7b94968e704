"""Run the Alembic migrations shipped in ``service/migrations`` from code.

``upgrade(url_or_engine)`` brings a database to the newest schema (``chtc run --migrate`` and ``chtc db
upgrade`` call it); ``current_revision`` and ``head_revision`` tell whether a database is up to date. The same
scripts work from the Alembic CLI: ``alembic -c service/alembic.ini upgrade head`` (URL from
``CHTC_DATABASE__URL``).

A migration may rewrite every stored sample (0007, 0008: ~45 s for 20 spindle-days), so it runs without the
serving timeouts: on PostgreSQL its transaction sets ``statement_timeout``, ``lock_timeout`` and
``idle_in_transaction_session_timeout`` to 0 (off) whatever the engine's connections set, and the service
gives it an engine of its own, outside the client-side watchdog (``service.host.persistence``). A frozen
link is still noticed, by the kernel (the connection's TCP keepalives and ``tcp_user_timeout``). Progress is
logged: each revision applied with its wall time, and every ``PROGRESS_EVERY_S`` while one runs.
"""

from __future__ import annotations

import logging
import threading
import time
from pathlib import Path
from typing import Any

from alembic import command
from alembic.config import Config
from alembic.runtime.migration import MigrationContext
from alembic.script import ScriptDirectory
from sqlalchemy import Connection, Engine
from sqlalchemy import exc as sa_exc

from service.store.engine import create_db_engine
from service.store.sqlerrors import translate

MIGRATIONS_DIR = Path(__file__).resolve().parent.parent / "migrations"
PROGRESS_EVERY_S = 10.0  # wall seconds between "still running" lines of a long revision

log = logging.getLogger(__name__)


def alembic_config(url: str | None = None) -> Config:
    """An Alembic ``Config`` pointing at the packaged scripts (no ini file needed)."""
    cfg = Config()
    cfg.set_main_option("script_location", str(MIGRATIONS_DIR))
    if url is not None:
        cfg.set_main_option("sqlalchemy.url", url.replace("%", "%%"))
    return cfg


def upgrade(target: str | Engine, revision: str = "head", *, spindle_id: str | None = None) -> None:
    """Upgrade the database at ``target`` (URL or engine) to ``revision``; raises ``DatabaseError`` types.

    ``spindle_id``: the id revision ``0007`` gives the rows stored before it (default ``CHTC_SPINDLE__ID``,
    else ``spindle1``)."""
    engine, owned = _engine(target)
    try:
        with engine.begin() as conn:
            _no_serving_timeouts(conn)
            cfg = alembic_config()
            cfg.attributes["connection"] = conn
            if spindle_id is not None:
                cfg.attributes["spindle_id"] = spindle_id
            with _Progress(conn, revision) as progress:
                cfg.attributes["on_version_apply"] = (progress.step_done,)
                command.upgrade(cfg, revision)
    except sa_exc.SQLAlchemyError as err:
        raise translate(err, f"migrate to {revision}") from err
    finally:
        if owned:
            engine.dispose()


def _no_serving_timeouts(conn: Connection) -> None:
    """PostgreSQL: this transaction runs as long as the migration needs (``SET LOCAL``: it ends with it)."""
    if conn.dialect.name == "postgresql":
        for name in ("statement_timeout", "lock_timeout", "idle_in_transaction_session_timeout"):
            conn.exec_driver_sql(f"SET LOCAL {name} = 0")


class _Progress:
    """Logs the migration's start, each revision applied (wall s), and "still running" every
    ``PROGRESS_EVERY_S`` while one runs (a thread: a revision is one long statement)."""

    def __init__(self, conn: Connection, target: str) -> None:
        self._target = target
        self._from = MigrationContext.configure(conn).get_current_revision()
        self._t0 = self._step_t0 = time.monotonic()
        self._steps = 0
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._tick, name="chtc-migrate-progress", daemon=True)

    def __enter__(self) -> _Progress:
        log.info("migrate: from revision %s to %s", self._from or "(none)", self._target)
        self._thread.start()
        return self

    def __exit__(self, exc_type: object, exc: object, tb: object) -> None:
        self._stop.set()
        self._thread.join(timeout=1.0)
        took = time.monotonic() - self._t0
        if exc is None:
            log.info("migrate: done, %d revision(s) in %.1f s", self._steps, took)
        else:
            log.error(
                "migrate: failed after %.1f s (%d revision(s) applied, rolled back): %s",
                took,
                self._steps,
                exc,
            )

    def step_done(self, *, step: Any, **_: Any) -> None:
        now = time.monotonic()
        with self._lock:
            took, self._step_t0 = now - self._step_t0, now
            self._steps += 1
        down = ",".join(step.down_revision_ids) or "(none)"
        up = step.up_revision_id if step.is_upgrade else ",".join(step.down_revision_ids)
        frm = down if step.is_upgrade else step.up_revision_id
        log.info("migrate: %s -> %s applied in %.1f s", frm, up, took)

    def _tick(self) -> None:
        while not self._stop.wait(PROGRESS_EVERY_S):
            with self._lock:
                running = time.monotonic() - self._step_t0
            log.info("migrate: revision %d still running (%.0f s so far)", self._steps + 1, running)


def downgrade(target: str | Engine, revision: str, *, spindle_id: str | None = None) -> None:
    """Downgrade the database at ``target`` to ``revision`` (``"base"``: drop everything); below ``0007`` only
    ``spindle_id``'s rows are kept (default as in ``upgrade``)."""
    engine, owned = _engine(target)
    try:
        with engine.begin() as conn:
            cfg = alembic_config()
            cfg.attributes["connection"] = conn
            if spindle_id is not None:
                cfg.attributes["spindle_id"] = spindle_id
            command.downgrade(cfg, revision)
    finally:
        if owned:
            engine.dispose()


def current_revision(target: str | Engine) -> str | None:
    """The revision the database is at; None for a database never migrated."""
    engine, owned = _engine(target)
    try:
        with engine.connect() as conn:
            return MigrationContext.configure(conn).get_current_revision()
    except sa_exc.SQLAlchemyError as err:
        raise translate(err, "read schema revision") from err
    finally:
        if owned:
            engine.dispose()


def head_revision() -> str:
    """The newest revision shipped with this version."""
    head = ScriptDirectory.from_config(alembic_config()).get_current_head()
    assert head is not None
    return head


def _engine(target: str | Engine) -> tuple[Engine, bool]:
    if isinstance(target, Engine):
        return target, False
    return create_db_engine(target), True
