"""A probe reading of the axial growth in service (``ProbeMeasurement``): what the mechanical posterior
absorbs (``service.estimate.probe``), the store keeps (``probe_measurements``) and
``/compensation/measurements`` serves.

Errors::

    ProbeError(ServiceError, ValueError)   a reading of the wrong shape or value (the field named)
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from datetime import datetime

from service.contracts.columns import Column, finite
from service.contracts.errors import RecordError
from service.errors import ServiceError

__all__ = ["PROBES_KEPT", "FixtureOffset", "ProbeError", "ProbeMeasurement"]

PROBES_KEPT = 1000  # readings kept in memory and restored at start (listed by GET), the newest


class ProbeError(ServiceError, ValueError):
    """A probe reading that cannot be used; the message names the field."""


@dataclass(frozen=True, kw_only=True)
class ProbeMeasurement:
    """A probe reading: ``at`` (UTC) its instant, ``axial_um`` the tool's axial position relative to the
    commissioned zero and its 1σ ``sd_um`` [µm]; ``features`` (2, 3) [µm] the field's feature row then and
    ``field_var_um2`` [µm²] the served growth's variance from the field (and the zero) then; the outcome:
    ``predicted_um`` and ``sigma_um`` (√S) before it, the innovation ``innovation_um``, ``accepted``,
    ``offset_step`` (absorbed as a step of the fixture offset: gated, right after a consistent gated one;
    ``service.estimate.probe``); ``set_by``/``source`` who sent it; ``id`` the stored row (None: not stored
    yet)."""

    at: datetime
    axial_um: float
    sd_um: float
    features: tuple[tuple[float, ...], ...]
    field_var_um2: float
    predicted_um: float
    sigma_um: float
    innovation_um: float
    accepted: bool
    offset_step: bool = False
    set_by: str = "api"
    source: str = "api"
    id: int | None = None
    recorded_at: datetime | None = field(default=None, compare=False)  # UTC when the service took it (stored)

    def __post_init__(self) -> None:
        vals = (
            self.axial_um,
            self.sd_um,
            self.field_var_um2,
            self.predicted_um,
            self.sigma_um,
            self.innovation_um,
        )
        flat = [float(v) for r in self.features for v in r]
        if not all(math.isfinite(v) for v in (*vals, *flat)) or len(flat) != 6:
            raise ProbeError("ProbeMeasurement: finite values and a 2×3 feature row needed")
        for name in ("at", "recorded_at"):
            t = getattr(self, name)
            if t is not None and t.utcoffset() is None:
                raise ProbeError(f"ProbeMeasurement.{name}: naive datetime {t.isoformat()}; need UTC")

    @property
    def sigma_ratio(self) -> float:
        """|ν| / √S: how many predicted σ the reading lies off."""
        return abs(self.innovation_um) / self.sigma_um if self.sigma_um > 0 else math.inf

    def values(self) -> dict[str, Column]:
        """The ``probe_measurements`` row (``service.store``); ``recorded_at`` must be set."""
        if self.recorded_at is None:
            raise RecordError("ProbeMeasurement.recorded_at: unset; the stored reading needs it")
        return {
            "at": self.at,
            "recorded_at": self.recorded_at,
            "axial_um": float(self.axial_um),
            "sd_um": float(self.sd_um),
            "features": [finite(v) for r in self.features for v in r],  # row major
            "field_var_um2": float(self.field_var_um2),
            "predicted_um": float(self.predicted_um),
            "sigma_um": float(self.sigma_um),
            "innovation_um": float(self.innovation_um),
            "accepted": bool(self.accepted),
            "offset_step": bool(self.offset_step),
            "set_by": self.set_by[:64],
            "source": self.source[:16],
        }


@dataclass(frozen=True, kw_only=True)
class FixtureOffset:
    """The fixture or tool-holder offset the probe readings measured (``service.estimate.probe``): ``um`` the
    estimate b [µm] (+ towards the tool, added to the served axial growth), ``sd_um`` its 1σ, ``cov_mech_um``
    its covariance with θ = (s, a_s, a_h) (3,) [µm], ``readings`` absorbed since the commissioning, ``at``
    (UTC) the last one absorbed and ``steps`` of them taken as a step of the offset."""

    um: float
    sd_um: float
    cov_mech_um: tuple[float, float, float]
    readings: int
    at: datetime
    steps: int = 0

    def __post_init__(self) -> None:
        if not all(math.isfinite(v) for v in (self.um, self.sd_um, *self.cov_mech_um)) or self.sd_um < 0:
            raise ProbeError("FixtureOffset: finite values and sd_um >= 0 needed")
        if self.at.utcoffset() is None:
            raise ProbeError(f"FixtureOffset.at: naive datetime {self.at.isoformat()}; need UTC")
