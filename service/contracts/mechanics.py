"""A commissioning of the served growth's mechanics (``MechanicsCalibration``): θ = (s, a_s, a_h) and its
covariance, made by ``service.shell.commissioning``, stored (``mechanics_calibrations``), updated by probe
readings (``service.estimate.probe``) and served by ``/compensation`` (docs/commissioning.md); and how the
shipped example thermal test is told apart (``is_shipped_example``: another machine's mechanics).

Errors::

    MechanicsError(ServiceError, ValueError)   a calibration of the wrong shape or value (the field named)
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from datetime import datetime
from typing import Any

import numpy as np
from numpy.typing import NDArray

from service.contracts.columns import Column, finite, plain_dict
from service.errors import ServiceError

__all__ = [
    "EXAMPLE_MARK",
    "EXAMPLE_NOTE",
    "MECH_PARAMS",
    "MechanicsCalibration",
    "MechanicsError",
    "is_shipped_example",
]

Array = NDArray[np.float64]
# the first line of the shipped example's displacement file (service/data/example_thermal_test_*): another
# machine's mechanics; a running service refuses it outside the demo, a stored one is marked (issue 41)
EXAMPLE_MARK = "# chtc: shipped example"
EXAMPLE_NOTE = (
    "the shipped example thermal test (service/data/example_thermal_test_*): the virtual plant's mechanics, "
    "not this spindle's; commission from a test measured on this spindle (docs/commissioning.md)"
)


def is_shipped_example(displacements_csv: str) -> bool:
    """Whether the displacement CSV's text is the shipped example's (its ``EXAMPLE_MARK`` line)."""
    return any(line.startswith(EXAMPLE_MARK) for line in displacements_csv.splitlines()[:5])


MECH_PARAMS = ("restraint", "alpha_shaft", "alpha_housing")


class MechanicsError(ServiceError, ValueError):
    """A bad mechanical calibration or basis; the message names the field."""


@dataclass(frozen=True, kw_only=True)
class MechanicsCalibration:
    """A stored commissioning of the mechanics: θ = (s, a_s, a_h) ``x`` and its posterior covariance ``cov``
    (3, 3); ``at`` (UTC) when it was made, ``set_by`` who ran it, ``source`` (``cli``/``api``), the SHA-256 of
    the test's files (``sources``: role -> hex), the fit's residual RMS and max [µm], its verdict
    (``explained``) and the whole report (``report``, JSON-ready)."""

    x: tuple[float, float, float]
    cov: tuple[tuple[float, ...], ...]
    at: datetime
    set_by: str
    source: str
    sources: dict[str, str] = field(default_factory=dict)
    residual_rms_um: float = math.nan
    residual_max_um: float = math.nan
    explained: bool = False
    report: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        x = np.asarray(self.x, dtype=float)
        c = np.asarray(self.cov, dtype=float)
        if x.shape != (3,) or not np.all(np.isfinite(x)):
            raise MechanicsError(f"x: expected 3 finite values (s, a_s, a_h), got {self.x!r}")
        if not 0.0 <= x[0] <= 1.0 or not (0.5 < x[1] < 1.5 and 0.5 < x[2] < 1.5):
            raise MechanicsError(f"x: restraint in [0, 1] and α factors in (0.5, 1.5), got {self.x!r}")
        if c.shape != (3, 3) or not np.all(np.isfinite(c)) or np.any(np.diag(c) < 0):
            raise MechanicsError(f"cov: expected a finite (3, 3) covariance, got shape {c.shape}")
        if self.at.tzinfo is None:
            raise MechanicsError("at: must be timezone-aware (UTC)")

    @property
    def mean(self) -> Array:
        return np.asarray(self.x, dtype=float)

    @property
    def covariance(self) -> Array:
        c = np.asarray(self.cov, dtype=float)
        return np.asarray(0.5 * (c + c.T))

    @property
    def sd(self) -> Array:
        return np.asarray(np.sqrt(np.maximum(np.diag(self.covariance), 0.0)))

    def as_dict(self) -> dict[str, float]:
        """Name -> value."""
        return {n: float(v) for n, v in zip(MECH_PARAMS, self.x, strict=True)}

    def values(self) -> dict[str, Column]:
        """The ``mechanics_calibrations`` row (``service.store``)."""
        return {
            "at": self.at,
            "set_by": self.set_by[:64],
            "source": self.source[:16],
            "restraint": float(self.x[0]),
            "alpha_shaft": float(self.x[1]),
            "alpha_housing": float(self.x[2]),
            "cov": [finite(v) for r in self.cov for v in r],  # row major
            "residual_rms_um": finite(self.residual_rms_um),
            "residual_max_um": finite(self.residual_max_um),
            "explained": bool(self.explained),
            "temperatures_sha256": self.sources.get("temperatures", "")[:64],
            "canlog_sha256": None if (c := self.sources.get("canlog")) is None else c[:64],
            "displacements_sha256": self.sources.get("displacements", "")[:64],
            "report": plain_dict(self.report),
        }
