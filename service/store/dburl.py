"""The database URL as the store uses it: the common spellings of a PostgreSQL URL accepted.

Heroku-style ``postgres://…`` and SQLAlchemy's ``postgresql://…`` (whose default driver, psycopg2, is not
installed) both mean the store's one PostgreSQL driver, ``postgresql+psycopg://…``; every other URL is left as
written (``service.commands._common.check_database_url`` says what to write instead). Pure: no I/O.
"""

from __future__ import annotations

__all__ = ["normalize_database_url"]

_POSTGRES = ("postgres://", "postgresql://", "postgres+psycopg://")
_CANONICAL = "postgresql+psycopg://"


def normalize_database_url(url: str) -> str:
    """``url`` with a PostgreSQL scheme spelled ``postgresql+psycopg://`` (other URLs unchanged)."""
    head = url[: url.find("://") + 3].lower() if "://" in url else ""
    if head in _POSTGRES:
        return _CANONICAL + url[len(head) :]
    return url
