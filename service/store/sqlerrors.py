"""SQLAlchemy errors translated once into the typed tree of ``service.store.errors``."""

from __future__ import annotations

from sqlalchemy import exc as sa_exc

from service.store.errors import DatabaseError, DatabaseUnavailableError, RecordRejectedError

__all__ = ["is_transient", "translate"]


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
    return RecordRejectedError(f"{what}: rejected: {detail}")
