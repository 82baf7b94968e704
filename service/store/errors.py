"""Errors of the persistence layer.

::

    DatabaseError(Exception)
    ├── DatabaseUnavailableError(DatabaseError, ConnectionError)   cannot connect, locked, not migrated
    ├── RecordNotFoundError(DatabaseError, LookupError)            unknown id (names the table and id)
    └── RecordError(DatabaseError, ValueError)                     a record the database refuses (names why)

SQLAlchemy errors are translated into these in ``service.store.sqlerrors`` (this module imports no SQLAlchemy,
so the pure records can raise ``RecordError``).
"""

from __future__ import annotations


class DatabaseError(Exception):
    """Base of the persistence errors."""


class DatabaseUnavailableError(DatabaseError, ConnectionError):
    """The database cannot be reached or used right now; retrying later may succeed."""


class RecordNotFoundError(DatabaseError, LookupError):
    """No row with this id."""


class RecordError(DatabaseError, ValueError):
    """The database rejects this record (duplicate id, missing parent, bad value); retrying will not help."""
