"""Errors of the service's contracts (part of the service's tree, ``service.errors``).

::

    ServiceError (service.errors)
    └── RecordError(ServiceError, ValueError)     a record that breaks its contract: naive datetime, wrong
                                                  length, unknown outcome (names the record and the field)

``service.store.errors.RecordRejectedError`` (a record the database refuses) is also a ``RecordError``.
"""

from __future__ import annotations

from service.errors import ServiceError

__all__ = ["RecordError"]


class RecordError(ServiceError, ValueError):
    """A record is not valid (or, as ``RecordRejectedError``, the database refuses it): retrying will not
    help. The message names the record type and the field."""
