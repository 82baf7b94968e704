"""A sensor-offset baseline (``Calibration``): taken by ``service.acquire.calibration``, stored as it is
(``offset_calibrations``: ``values()`` is its row), applied by the core and served as ``OffsetBaseline``.

A baseline that breaks its contract (a naive time, offsets and 1σ of different lengths, an unknown source, no
sample, a window ending before it starts) raises ``RecordError`` naming the field.
"""

from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime

import numpy as np
from numpy.typing import NDArray

from service.contracts.columns import Column, check_times, finite_list
from service.contracts.errors import RecordError

__all__ = ["CALIBRATION_SOURCES", "Calibration"]

Array = NDArray[np.float64]
# "auto": a rest detected, "manual": an operator's request, "commissioning": the commissioning thermal test's
# initial rest, kept in the stored commissioning (``service.contracts.commissionbaseline``)
CALIBRATION_SOURCES = ("auto", "manual", "commissioning")


@dataclass(frozen=True, eq=False, kw_only=True)
class Calibration:
    """A baseline: per-channel offsets (32,) °C (NaN: no usable data in the window, not corrected) and their
    1σ (32,) °C, the window [t_from, t_to] (UTC) and how it was taken (``CALIBRATION_SOURCES``)."""

    offsets_c: Array
    sd_c: Array
    t_from: datetime
    t_to: datetime
    samples: int
    source: str

    def __post_init__(self) -> None:
        check_times(self)
        if len(self.sd_c) != len(self.offsets_c):
            raise RecordError(
                f"Calibration.sd_c: expected {len(self.offsets_c)} values, got {len(self.sd_c)}"
            )
        if self.source not in CALIBRATION_SOURCES:
            raise RecordError(f"Calibration.source: {self.source!r} not in {CALIBRATION_SOURCES}")
        if self.samples < 1:
            raise RecordError(f"Calibration.samples: need >= 1, got {self.samples}")
        if self.t_to < self.t_from:
            raise RecordError("Calibration.t_to: before t_from")

    def values(self) -> dict[str, Column]:
        """The ``offset_calibrations`` row (``service.store``): NaN offsets become NULL."""
        return {
            "t_from": self.t_from,
            "t_to": self.t_to,
            "source": self.source,
            "samples": int(self.samples),
            "offsets_c": finite_list(self.offsets_c),
            "sd_c": finite_list(self.sd_c),
        }

    def applied(self) -> Array:
        """The offsets to subtract (32,) °C: 0 where the baseline had no data."""
        return np.where(np.isfinite(self.offsets_c), self.offsets_c, 0.0)
