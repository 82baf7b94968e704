"""A sensor channel the live state leaves out as stuck or drifting (found by
``service.estimate.sensorfaults``; served by ``/chtc``, ``/compensation``, the dashboard and the log)."""

from __future__ import annotations

import enum
from dataclasses import dataclass

__all__ = ["FaultKind", "SensorFault"]


class FaultKind(enum.StrEnum):
    """What is wrong with a channel the DAQ does not flag."""

    STUCK = "stuck"  # the reading froze while the noise or the model should move it
    DRIFT = "drift"  # the reading walks away from the model's prediction (CUSUM of the innovations)


@dataclass(frozen=True)
class SensorFault:
    """Channel ``channel`` (1-based; ``index`` 0-based in the sample) out of the live state's updates since
    ``since_t`` [s, UTC epoch]: ``kind`` and a human ``detail`` (the evidence)."""

    channel: int
    index: int
    kind: FaultKind
    since_t: float
    detail: str
