"""Errors of the persistence layer (part of the service's tree, ``service.errors``).

::

    ServiceError (service.errors)
    └── DatabaseError(ServiceError)
        ├── DatabaseUnavailableError(DatabaseError, ConnectionError)     unusable now; a retry may succeed
        │   ├── DatabaseBusyError(DatabaseUnavailableError)              every API read slot is taken
        │   ├── DatabaseTimeoutError(DatabaseUnavailableError, TimeoutError)  a read did not answer in time
        │   └── SchemaError(DatabaseUnavailableError)                    reachable, not migrated (--migrate)
        ├── RecordNotFoundError(DatabaseError, LookupError)              unknown id (names table and id)
        └── RecordRejectedError(DatabaseError, RecordError)              the database refuses a record
            └── StoredCalibrationError(RecordRejectedError)              (service.store.calibrations) a
                                                                         stored baseline that cannot be used

``RecordError`` (``service.contracts.errors``, re-exported here) is what an invalid record raises at
construction; ``RecordRejectedError`` is also one, so ``except RecordError`` catches both. SQLAlchemy errors
are translated into this tree in ``service.store.sqlerrors`` (this module imports no SQLAlchemy). None of
these is an API error: the service turns a database that cannot answer into
``service.contracts.errors.NotReadyError`` where it serves the API (``service.shell.archive``).
"""

from __future__ import annotations

from service.contracts.errors import RecordError
from service.errors import ServiceError

__all__ = [
    "DatabaseBusyError",
    "DatabaseError",
    "DatabaseTimeoutError",
    "DatabaseUnavailableError",
    "RecordError",
    "RecordNotFoundError",
    "RecordRejectedError",
    "SchemaError",
]


class DatabaseError(ServiceError):
    """Base of the persistence errors."""


class DatabaseUnavailableError(DatabaseError, ConnectionError):
    """The database cannot be reached or used right now; retrying later may succeed."""


class DatabaseBusyError(DatabaseUnavailableError):
    """Every database read slot is taken (the database is slow or hung): try again later."""


class DatabaseTimeoutError(DatabaseUnavailableError, TimeoutError):
    """The database did not answer a read in time."""


class SchemaError(DatabaseUnavailableError):
    """The database answers, but its schema is missing or older than this version (``--migrate``)."""


class RecordNotFoundError(DatabaseError, LookupError):
    """No row with this id."""


class RecordRejectedError(DatabaseError, RecordError):
    """The database rejects this record (duplicate id, missing parent, bad value); retrying will not help."""
