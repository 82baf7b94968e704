"""What a stored record's column holds (``Column``, ``JsonValue``) and the checks and conversions every record
shares: ``finite`` (None for NaN/±inf: JSON and SQL have no NaN), ``plain_dict`` (JSON-safe copies of numpy
values), ``check_times`` (UTC datetimes only).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import fields
from datetime import datetime
from typing import TYPE_CHECKING, SupportsFloat, TypeVar

import numpy as np

from service.contracts.errors import RecordError

if TYPE_CHECKING:
    from _typeshed import DataclassInstance

__all__ = [
    "Column",
    "ColumnScalar",
    "JsonValue",
    "check_times",
    "finite",
    "finite_list",
    "plain",
    "plain_dict",
]

K = TypeVar("K")

# What a JSON column holds (``diagnostics``): built by ``plain_dict`` from numpy values.
JsonValue = None | bool | int | float | str | list["JsonValue"] | dict[str, "JsonValue"]
ColumnScalar = datetime | int | float | str | bool | bytes | None
Column = ColumnScalar | list[float | None] | list[bool] | dict[str, JsonValue]


def finite(value: SupportsFloat | None) -> float | None:
    """``float(value)``, or None for None/NaN/±inf (JSON and SQL have no NaN)."""
    if value is None:
        return None
    x = float(value)
    return x if math.isfinite(x) else None


def finite_list(values: Iterable[SupportsFloat | None]) -> list[float | None]:
    return [finite(v) for v in values]


def check_times(record: DataclassInstance) -> None:
    for f in fields(record):
        value = getattr(record, f.name)
        if isinstance(value, datetime) and (value.tzinfo is None or value.utcoffset() is None):
            raise RecordError(
                f"{type(record).__name__}.{f.name}: naive datetime {value.isoformat()}; need UTC"
            )


def plain(value: object) -> JsonValue:
    """JSON-safe copy: numpy scalars/arrays to Python, non-finite floats to None, keys to str."""
    if isinstance(value, Mapping):
        return plain_dict(value)
    if isinstance(value, np.ndarray | np.generic):
        value = value.tolist()
    if isinstance(value, list | tuple):
        return [plain(v) for v in value]
    if isinstance(value, float):
        return finite(value)
    if value is None or isinstance(value, bool | int | str):
        return value
    raise RecordError(f"diagnostics: {type(value).__name__} is not JSON")


def plain_dict(value: Mapping[K, object]) -> dict[str, JsonValue]:
    return {str(k): plain(v) for k, v in value.items()}
