"""Column types: :class:`UtcDateTime` stores UTC and always returns timezone-aware UTC datetimes;
:class:`TemperatureArray` is ``real[]`` on PostgreSQL and JSON elsewhere."""

from __future__ import annotations

from datetime import UTC, datetime
from typing import Any

import numpy as np
from sqlalchemy import JSON, REAL, DateTime
from sqlalchemy.dialects.postgresql import ARRAY
from sqlalchemy.engine import Dialect
from sqlalchemy.types import TypeDecorator, TypeEngine


class UtcDateTime(TypeDecorator[datetime]):
    """``TIMESTAMP WITH TIME ZONE`` on PostgreSQL; naive UTC text on SQLite (no zones), made aware on read.

    Naive datetimes are refused on write: every timestamp in the service is aware UTC, and guessing a zone
    would silently shift stored data.
    """

    impl = DateTime(timezone=True)
    cache_ok = True

    def process_bind_param(self, value: object, dialect: Dialect) -> datetime | None:
        if value is None:
            return None
        if not isinstance(value, datetime):
            raise TypeError(f"expected a datetime, got {type(value).__name__}")
        if value.tzinfo is None or value.utcoffset() is None:
            raise ValueError(f"naive datetime {value.isoformat()} refused; use an aware UTC datetime")
        value = value.astimezone(UTC)
        return value.replace(tzinfo=None) if dialect.name == "sqlite" else value

    def process_result_value(self, value: datetime | None, dialect: Dialect) -> datetime | None:
        if value is None:
            return None
        if value.tzinfo is None:
            return value.replace(tzinfo=UTC)
        return value.astimezone(UTC)


class TemperatureArray(TypeDecorator[list[float | None]]):
    """Per-channel temperatures [°C]: ``real[]`` on PostgreSQL (4 bytes a value, NULL kept), a JSON array
    elsewhere. A ``real`` read back is the shortest decimal that is the same float32 (23.45, not
    23.450000762939453): the data come at 0.01 °C, which float32 holds to 7 significant digits."""

    impl = JSON
    cache_ok = True

    def load_dialect_impl(self, dialect: Dialect) -> TypeEngine[Any]:
        if dialect.name == "postgresql":
            array: TypeEngine[Any] = ARRAY(REAL())
            return dialect.type_descriptor(array)
        return dialect.type_descriptor(JSON())

    def process_result_value(self, value: object, dialect: Dialect) -> list[float | None] | None:
        if value is None:
            return None
        values = list(value)  # type: ignore[call-overload]
        if dialect.name != "postgresql":
            return values
        return [None if v is None else float(str(np.float32(v))) for v in values]
