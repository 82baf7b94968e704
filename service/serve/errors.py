"""The outlets' errors (``service.errors`` draws the tree)::

OutletError(ServiceError, RuntimeError)    an outlet cannot be loaded, configured or started
"""

from __future__ import annotations

from service.errors import ServiceError

__all__ = ["OutletError"]


class OutletError(ServiceError, RuntimeError):
    """An outlet (REST, OPC UA, MQTT) cannot be loaded, configured or started; the message says which."""
