"""Sensor offset baselines in the database: ``Calibration`` <-> ``offset_calibrations`` rows.

The service writes every baseline it takes through the buffered writer (``Calibration.values`` is its row)
and restores the newest at start-up (``restore_calibration``), so the offsets survive a restart instead of
falling back to "no baseline" (wider CIs) until the spindle rests again. A stored row that does not make a
baseline (wrong channel count, a negative or missing 1σ, an unknown source) raises ``StoredCalibrationError``
naming the row and the field; the row stays in the table.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np

from service.contracts.calibration import CALIBRATION_SOURCES, Calibration
from service.store.errors import RecordRejectedError

if TYPE_CHECKING:
    from sqlalchemy.orm import Session

    from service.store.models import OffsetCalibrationRow

__all__ = ["StoredCalibrationError", "calibration_from_row", "restore_calibration"]


class StoredCalibrationError(RecordRejectedError):
    """A stored offset baseline that cannot be used; the message names the row and the field."""


def calibration_from_row(row: OffsetCalibrationRow, *, n_channels: int = 32) -> Calibration:
    """The ``Calibration`` stored in ``row`` (``OffsetCalibrationRow``); ``StoredCalibrationError`` if bad."""

    def bad(field: str, why: str) -> StoredCalibrationError:
        return StoredCalibrationError(f"offset_calibrations row {row.id}: {field}: {why}")

    offsets, sd = (
        _floats(row.offsets_c, "offsets_c", n_channels, bad),
        _floats(row.sd_c, "sd_c", n_channels, bad),
    )
    if not all(s is not None and s > 0 for s in sd):
        raise bad("sd_c", "every channel needs a finite 1σ > 0 °C")
    if row.source not in CALIBRATION_SOURCES:
        raise bad("source", f"{row.source!r} not in {CALIBRATION_SOURCES}")
    if not isinstance(row.samples, int) or row.samples < 1:
        raise bad("samples", f"need an integer >= 1, got {row.samples!r}")
    if row.t_to < row.t_from:
        raise bad("t_to", f"{row.t_to.isoformat()} is before t_from {row.t_from.isoformat()}")
    return Calibration(
        offsets_c=np.array([np.nan if x is None else x for x in offsets], dtype=float),
        sd_c=np.array(sd, dtype=float),
        t_from=row.t_from,
        t_to=row.t_to,
        samples=int(row.samples),
        source=str(row.source),
    )


def _floats(
    values: object, field: str, n: int, bad: Callable[[str, str], StoredCalibrationError]
) -> list[float | None]:
    if not isinstance(values, list) or len(values) != n:
        got = f"{len(values)} values" if isinstance(values, list) else type(values).__name__
        raise bad(field, f"expected a list of {n} values (one per channel), got {got}")
    out: list[float | None] = []
    for i, x in enumerate(values):
        if x is not None and (isinstance(x, bool) or not isinstance(x, int | float) or not math.isfinite(x)):
            raise bad(field, f"channel {i + 1}: {x!r} is not a temperature in °C")
        out.append(None if x is None else float(x))
    return out


def restore_calibration(session: Session, *, n_channels: int = 32) -> Calibration | None:
    """The newest stored baseline, None if there is none; ``StoredCalibrationError`` if it is unusable."""
    from service.store.repository import last_offset_calibration

    row = last_offset_calibration(session)
    return None if row is None else calibration_from_row(row, n_channels=n_channels)
