"""Errors of the persistence layer.

::

    DatabaseError(Exception)
    ├── DatabaseUnavailableError(DatabaseError, ConnectionError)   cannot connect, locked, not migrated
    ├── RecordNotFoundError(DatabaseError, LookupError)            unknown id (names the table and id)
    └── RecordError(DatabaseError, ValueError)                     a record the database refuses (names why)

SQLAlchemy errors are translated in :func:`translate` (used by the repository helpers and the writer).
"""

from __future__ import annotations

from sqlalchemy import exc as sa_exc


class DatabaseError(Exception):
    """Base of the persistence errors."""


class DatabaseUnavailableError(DatabaseError, ConnectionError):
    """The database cannot be reached or used right now; retrying later may succeed."""


class RecordNotFoundError(DatabaseError, LookupError):
    """No row with this id."""


class RecordError(DatabaseError, ValueError):
    """The database rejects this record (duplicate id, missing parent, bad value); retrying will not help."""


def is_transient(err: BaseException) -> bool:
    """True for errors a retry can fix: lost connection, locks, timeouts, tables missing (not migrated)."""
    if isinstance(err, sa_exc.IntegrityError | sa_exc.DataError):
        return False
    if isinstance(err, sa_exc.DBAPIError):
        return True
    return isinstance(err, sa_exc.TimeoutError | sa_exc.DisconnectionError | ConnectionError | TimeoutError)


def translate(err: Exception, what: str) -> DatabaseError:
    """The typed error for a SQLAlchemy error raised while doing ``what`` (e.g. "insert identifications")."""
    detail = str(getattr(err, "orig", None) or err).strip().splitlines()[0]
    if is_transient(err):
        return DatabaseUnavailableError(f"{what}: database unavailable: {detail}")
    return RecordError(f"{what}: rejected: {detail}")
