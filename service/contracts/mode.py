"""The identification mode (``identification.mode``), fixed for a service's life.

Each mode has one serving strategy in ``service.core.serving``, which decides what runs (the per-condition
schedule, the speed map, or both) and which identification is served.
"""

from __future__ import annotations

import enum

__all__ = ["IdentificationMode"]


class IdentificationMode(enum.StrEnum):
    """How H is identified and served (docs/design/hmap.md; the values are the settings' spelling)."""

    PER_CONDITION = "per_condition"  # the paper's protocol: one H per held condition
    SPEED_MAP = "speed_map"  # H = F(n, Ti) over a rolling window, re-fitted on condition changes
    COMBINED = "combined"  # both: a held condition's own per-condition H, the map's elsewhere
