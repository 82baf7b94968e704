"""What a newcomer met (issue 41 section 5): each test failed before its fix."""

from __future__ import annotations

import pytest
from sqlalchemy import text

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
