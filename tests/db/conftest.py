"""Fixtures: every database test runs on real SQLite (a temp file) and real PostgreSQL (a fresh schema)."""

from __future__ import annotations

import time
import uuid
from collections.abc import Callable, Iterator
from datetime import UTC, datetime

import pytest
import sqlalchemy as sa
from sqlalchemy.engine import make_url
from sqlalchemy.orm import Session, sessionmaker

from service.store import migrate
from service.store import repository as repo
from service.store.engine import DEFAULT_SPINDLE_ID, create_db_engine, make_session_factory


def pg_schema_url(base_url: str, schema: str, *, port: int | None = None) -> str:
    """``base_url`` with ``search_path`` set to ``schema`` (and optionally another port)."""
    url = make_url(base_url).update_query_dict({"options": f"-csearch_path={schema}"})
    if port is not None:
        url = url.set(port=port)
    return url.render_as_string(hide_password=False)


@pytest.fixture
def pg_schema(pg_url: str) -> Iterator[str]:
    """A fresh, empty schema, dropped after the test."""
    schema = f"chtc_test_{uuid.uuid4().hex[:12]}"
    admin = sa.create_engine(pg_url)
    with admin.begin() as conn:
        conn.execute(sa.text(f'CREATE SCHEMA "{schema}"'))
    try:
        yield schema
    finally:
        with admin.begin() as conn:
            conn.execute(sa.text(f'DROP SCHEMA "{schema}" CASCADE'))
        admin.dispose()


@pytest.fixture(params=["sqlite", pytest.param("postgres", marks=pytest.mark.postgres)])
def db_url(request: pytest.FixtureRequest, tmp_path: object) -> str:
    """An empty database: a SQLite file, or a PostgreSQL schema private to this test."""
    if request.param == "sqlite":
        return f"sqlite:///{tmp_path}/chtc-test.db"  # type: ignore[operator]
    schema = request.getfixturevalue("pg_schema")
    return pg_schema_url(request.getfixturevalue("pg_url"), schema)


@pytest.fixture
def engine(db_url: str) -> Iterator[sa.Engine]:
    """A migrated database."""
    eng = create_db_engine(db_url)
    migrate.upgrade(eng)
    yield eng
    eng.dispose()


@pytest.fixture
def factory(engine: sa.Engine) -> sessionmaker[Session]:
    """Sessions of the default spindle (registered)."""
    return spindle_factory(engine, DEFAULT_SPINDLE_ID)


def spindle_factory(engine: sa.Engine, spindle_id: str) -> sessionmaker[Session]:
    """Sessions of ``spindle_id``, registered in ``spindles``."""
    f = make_session_factory(engine, spindle_id=spindle_id)
    with repo.session_scope(f, "register") as s:
        repo.ensure_spindle(s, spindle_id, now=datetime.now(UTC))
    return f


def wait_until(predicate: Callable[[], bool], *, timeout_s: float = 15.0, what: str = "condition") -> None:
    """Poll ``predicate`` until true; fail after ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > deadline:
            pytest.fail(f"timed out after {timeout_s} s waiting for {what}")
        time.sleep(0.01)
