"""Run the Alembic migrations shipped in ``service/migrations`` from code.

``upgrade(url_or_engine)`` brings a database to the newest schema (``chtc run --migrate`` calls it);
``current_revision`` and ``head_revision`` tell whether a database is up to date. The same scripts work from
the Alembic CLI: ``alembic -c service/alembic.ini upgrade head`` (URL from ``CHTC_DATABASE__URL``).
"""

from __future__ import annotations

from pathlib import Path

from alembic import command
from alembic.config import Config
from alembic.runtime.migration import MigrationContext
from alembic.script import ScriptDirectory
from sqlalchemy import Engine
from sqlalchemy import exc as sa_exc

from service.store.engine import create_db_engine
from service.store.sqlerrors import translate

MIGRATIONS_DIR = Path(__file__).resolve().parent.parent / "migrations"


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
            cfg = alembic_config()
            cfg.attributes["connection"] = conn
            if spindle_id is not None:
                cfg.attributes["spindle_id"] = spindle_id
            command.upgrade(cfg, revision)
    except sa_exc.SQLAlchemyError as err:
        raise translate(err, f"migrate to {revision}") from err
    finally:
        if owned:
            engine.dispose()


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
