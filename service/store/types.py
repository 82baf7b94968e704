"""Column types: :class:`UtcDateTime` stores UTC and always returns timezone-aware UTC datetimes; the
samples' compact types (revision ``0008``): :class:`TemperatureArray` (``smallint[]`` centi-degrees on
PostgreSQL), :class:`Float32` (``real``) and :class:`QualityMap` (``bytea``), JSON or doubles of the same
values elsewhere."""

from __future__ import annotations

import math
from collections.abc import Mapping
from datetime import UTC, datetime
from typing import Any

import numpy as np
from sqlalchemy import JSON, REAL, DateTime, Double, LargeBinary, SmallInteger
from sqlalchemy.dialects.postgresql import ARRAY
from sqlalchemy.engine import Dialect
from sqlalchemy.types import TypeDecorator, TypeEngine

from drivers.quality import Quality


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
    """Per-channel temperatures [°C], kept to 0.01 °C (revision ``0008``): ``smallint[]`` of centi-degrees on
    PostgreSQL (2 bytes a value, NULL kept), a JSON array of the same rounded values elsewhere.

    Every backend stores what PostgreSQL can: a value is rounded to the nearest 0.01 °C on write
    (``centi_celsius``), so a read gives the same floats everywhere (``2345 / 100``, i.e. 23.45). Lossless for
    the default DAQ map (int16 at 0.01 °C/bit); a float32 map loses at most 0.005 °C, far below the sensors'
    ±0.3 °C offsets. A value beyond int16 (outside −327.68…327.67 °C, no spindle temperature) or not finite
    is stored as null ("no usable value")."""

    impl = JSON
    cache_ok = True

    def load_dialect_impl(self, dialect: Dialect) -> TypeEngine[Any]:
        if dialect.name == "postgresql":
            array: TypeEngine[Any] = ARRAY(SmallInteger())
            return dialect.type_descriptor(array)
        return dialect.type_descriptor(JSON())

    def process_bind_param(
        self, value: object, dialect: Dialect
    ) -> list[int | None] | list[float | None] | None:
        if value is None:
            return None
        centi = [centi_celsius(v) for v in value]  # type: ignore[attr-defined]
        if dialect.name == "postgresql":
            return centi
        return [None if c is None else c / CENTI for c in centi]

    def process_result_value(self, value: object, dialect: Dialect) -> list[float | None] | None:
        if value is None:
            return None
        values = list(value)  # type: ignore[call-overload]
        if dialect.name != "postgresql":
            return values
        return [None if c is None else c / CENTI for c in values]


CENTI = 100  # centi-degrees per °C
INT16_MIN, INT16_MAX = -32768, 32767


def centi_celsius(value: object) -> int | None:
    """°C → the nearest whole centi-degree (int16); None for None, a non-finite value or one beyond int16."""
    if value is None:
        return None
    x = float(value)  # type: ignore[arg-type]
    if not math.isfinite(x):
        return None
    c = round(x * CENTI)
    return c if INT16_MIN <= c <= INT16_MAX else None


def float32(value: float) -> float:
    """``value`` as PostgreSQL's ``real`` keeps it: the shortest decimal of the nearest float32 (23.45, not
    23.450000762939453). Exact for up to 6 significant decimal digits."""
    return float(str(np.float32(value)))


class Float32(TypeDecorator[float]):
    """A scalar stored as float32: ``real`` on PostgreSQL (4 bytes, not 8), a double elsewhere holding the
    same value (``float32`` on write), so every backend reads back the same float. Lossless for the default
    devices (rpm at 1 rpm/bit, N·m and °C at 0.01/bit: at most 6 significant digits); otherwise a relative
    error of at most 6e-8."""

    impl = Double
    cache_ok = True

    def load_dialect_impl(self, dialect: Dialect) -> TypeEngine[Any]:
        # not via dialect.type_descriptor: psycopg's adaptation of REAL renders (and so compares) as FLOAT
        return REAL() if dialect.name == "postgresql" else Double()

    def process_bind_param(self, value: object, dialect: Dialect) -> float | None:
        return None if value is None else float32(float(value))  # type: ignore[arg-type]

    def process_result_value(self, value: object, dialect: Dialect) -> float | None:
        return None if value is None else float32(float(value))  # type: ignore[arg-type]


class QualityMap(TypeDecorator[dict[str, str]]):
    """The channels whose quality is not ``ok``, ``{"7": "open_circuit"}`` (1-based channel → a
    ``drivers.quality.Quality`` label): ``bytea`` on PostgreSQL, two bytes a bad channel (the channel, 1–255,
    and the quality's code, ``Quality`` value 1–7), so a sample with every channel ok stores one byte (the
    JSON ``{}`` took three) and an open-circuit channel three instead of twenty-two; JSON elsewhere.

    A channel outside 1–255 or an unknown label is refused on write, on every backend (``ValueError`` naming
    it)."""

    impl = JSON
    cache_ok = True

    def load_dialect_impl(self, dialect: Dialect) -> TypeEngine[Any]:
        if dialect.name == "postgresql":
            return dialect.type_descriptor(LargeBinary())
        return dialect.type_descriptor(JSON())

    def process_bind_param(self, value: object, dialect: Dialect) -> bytes | dict[str, str] | None:
        if value is None:
            return None
        encoded = encode_quality_map(value)  # type: ignore[arg-type]  # (validates, on every backend)
        return encoded if dialect.name == "postgresql" else value  # type: ignore[return-value]

    def process_result_value(self, value: object, dialect: Dialect) -> dict[str, str] | None:
        if value is None:
            return None
        if dialect.name != "postgresql":
            return dict(value)  # type: ignore[call-overload]
        return decode_quality_map(bytes(value))  # type: ignore[call-overload]


_CODE_OF = {q.label: int(q) for q in Quality if q is not Quality.OK}
_LABEL_OF = {code: label for label, code in _CODE_OF.items()}


def encode_quality_map(bad: Mapping[str, str]) -> bytes:
    """``{"7": "open_circuit"}`` → ``b"\\x07\\x02"`` (pairs of channel, code; ascending channel)."""
    out = bytearray()
    for key, label in sorted(bad.items(), key=lambda kv: _channel(kv[0])):
        code = _CODE_OF.get(label)
        if code is None:
            raise ValueError(f"bad_channels[{key!r}]: unknown quality {label!r}; known: {sorted(_CODE_OF)}")
        out += bytes((_channel(key), code))
    return bytes(out)


def decode_quality_map(data: bytes) -> dict[str, str]:
    """The inverse of ``encode_quality_map``."""
    if len(data) % 2:
        raise ValueError(f"bad_channels: {len(data)} bytes, need pairs (channel, code)")
    out = {}
    for i in range(0, len(data), 2):
        channel, code = data[i], data[i + 1]
        if code not in _LABEL_OF:
            raise ValueError(f"bad_channels: channel {channel} has unknown quality code {code}")
        out[str(channel)] = _LABEL_OF[code]
    return out


def _channel(key: str) -> int:
    try:
        channel = int(key)
    except ValueError:
        raise ValueError(f"bad_channels: channel {key!r} is not a number") from None
    if not 1 <= channel <= 255:
        raise ValueError(f"bad_channels: channel {channel} outside 1..255")
    return channel
