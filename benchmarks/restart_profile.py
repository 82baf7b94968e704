"""The restart bench's profile and result type, shared by its two paths (``benchmarks.restart`` drives
them, ``benchmarks.restart_filter`` is the filter path): the plant run, its clock and truth, and one served
result. Both import this module; the filter path does not import ``benchmarks.restart``.
"""

from __future__ import annotations

from dataclasses import dataclass
from datetime import UTC, datetime
from typing import Any

import numpy as np

PROFILE = (
    (300.0, 0.0, 0.0, 22.0),  # idle and cold
    (3600.0, 3000.0, 5.0, 22.0),
    (2700.0, 4000.0, 6.0, 22.0),
    (2700.0, 5000.0, 8.0, 22.0),
)
T0 = datetime(2026, 3, 2, 6, 0, 0, tzinfo=UTC).timestamp()
DT_S = 10.0
BASELINE_SAMPLES = 30  # the idle 5 min at minute 0: the offset baseline of the filter path


@dataclass(frozen=True, kw_only=True)
class Served:
    """One successful identification: the condition's speed [rpm], H and CI [W/(m²·K)], window end [s]."""

    speed_rpm: float
    h: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    end_s: float
    identified: np.ndarray | None = None  # (7,) bool: flagged identified (core path)


def plant_run(seed: int) -> Any:
    """The profile's plant run (``model.plant.PlantRun``), samples every 10 s."""
    from model.geometry import load_spindle
    from model.plant import Segment, VirtualPlant

    return VirtualPlant(load_spindle(), seed=seed).run([Segment(*s) for s in PROFILE], dt_s=DT_S)


def truth(speed_rpm: float) -> np.ndarray:
    """The plant's H (7,) [W/(m²·K)] at the profile's condition of that speed."""
    from model.plant import h_true

    ambient = next(p[3] for p in PROFILE if p[1] == speed_rpm)
    return np.asarray(h_true(speed_rpm, ambient), dtype=float)
