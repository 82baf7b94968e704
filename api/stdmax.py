"""The field's largest 1σ for the ``/temperature-field`` metadata (shared by the schema and the renderer)."""

from __future__ import annotations

import numpy as np

from service.contracts.snapshots import FieldSnapshot

__all__ = ["std_max"]


def std_max(f: FieldSnapshot) -> float | None:
    """The field's largest finite 1σ (°C, rounded to 0.1 mK), None without one (``at=steady``)."""
    if f.std_c is None:
        return None
    finite = f.std_c[np.isfinite(f.std_c)]
    return round(float(finite.max()), 4) if finite.size else None
