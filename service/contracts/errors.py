"""Errors of the service's contracts (part of the service's tree, ``service.errors``): a record that breaks
its contract, and the failures of the service protocol (``service.serve.interface.ChtcService``) that the API
maps to HTTP codes (``api/errors.py``; any other ``ServiceError`` is a 500).

::

    ServiceError (service.errors)
    ├── RecordError(ServiceError, ValueError)     a record that breaks its contract: naive datetime, wrong
    │                                             length, unknown outcome (names the record and the field)
    ├── NotFoundError(ServiceError, LookupError)  unknown identification id / job id        -> 404
    ├── NoDataYetError(ServiceError)              nothing to show yet (no field, no data)    -> 503
    ├── BusyError(ServiceError)                   an identification is already running      -> 409
    ├── NotReadyError(ServiceError)               model not loaded / not enough good data   -> 503
    └── CommissioningError(ServiceError, ValueError)
                                                  a thermal test a commissioning cannot use (names the file,
                                                  line or field; ``service.shell.commissioning``) -> 422

``service.store.errors.RecordRejectedError`` (a record the database refuses) is also a ``RecordError``.
"""

from __future__ import annotations

from service.errors import ServiceError

__all__ = [
    "BusyError",
    "CommissioningError",
    "NoDataYetError",
    "NotFoundError",
    "NotReadyError",
    "RecordError",
]


class RecordError(ServiceError, ValueError):
    """A record is not valid (or, as ``RecordRejectedError``, the database refuses it): retrying will not
    help. The message names the record type and the field."""


class NotFoundError(ServiceError, LookupError):
    """An identification or job id that does not exist."""


class NoDataYetError(ServiceError):
    """Nothing to show yet (no field before the first identification, no samples)."""


class BusyError(ServiceError):
    """An identification is already queued or running."""


class NotReadyError(ServiceError):
    """The service cannot do what was asked yet (model not loaded, too little good data)."""


class CommissioningError(ServiceError, ValueError):
    """Input a commissioning cannot use; the message names the file, line or field."""
