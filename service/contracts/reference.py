"""The compensation reference (``CompensationReference``): the uniform temperature at which the served growth
is 0, how and by whom it was set (``service.estimate.reference`` takes it, docs/design/growth.md).

Errors::

    ReferenceError(ServiceError, ValueError)   a compensation reference that cannot be used (the field named)
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from datetime import datetime

from service.contracts.columns import Column
from service.errors import ServiceError

__all__ = ["MAX_SET_BY", "REFERENCE_SOURCES", "CompensationReference", "ReferenceError"]

REFERENCE_SOURCES = ("api", "cli", "first_start", "config")
MAX_SET_BY = 64  # characters of ``set_by`` kept


class ReferenceError(ServiceError, ValueError):
    """A compensation reference that cannot be used; the message names the field."""


@dataclass(frozen=True, kw_only=True)
class CompensationReference:
    """Where the controller was zeroed: the uniform ``temperature_c`` [°C] of growth 0, its 1σ ``sd_c`` [°C],
    when (``at``, UTC), how (``source``, one of ``REFERENCE_SOURCES``) and by whom (``set_by``)."""

    temperature_c: float
    sd_c: float
    at: datetime
    source: str
    set_by: str

    def __post_init__(self) -> None:
        if not math.isfinite(self.temperature_c) or not -50.0 <= self.temperature_c <= 200.0:
            raise ReferenceError(f"temperature_c: need a finite °C in [-50, 200], got {self.temperature_c!r}")
        if not math.isfinite(self.sd_c) or self.sd_c < 0.0:
            raise ReferenceError(f"sd_c: need a finite 1σ >= 0 °C, got {self.sd_c!r}")
        if self.at.tzinfo is None:
            raise ReferenceError("at: must be timezone-aware (UTC)")
        if self.source not in REFERENCE_SOURCES:
            raise ReferenceError(f"source: {self.source!r} not in {REFERENCE_SOURCES}")
        if not self.set_by.strip() or len(self.set_by) > MAX_SET_BY:
            raise ReferenceError(f"set_by: need 1..{MAX_SET_BY} characters, got {self.set_by!r}")

    def values(self) -> dict[str, Column]:
        """The ``compensation_references`` row (``service.store``)."""
        return {
            "at": self.at,
            "temperature_c": float(self.temperature_c),
            "sd_c": float(self.sd_c),
            "source": self.source[:16],
            "set_by": self.set_by[:64],
        }
