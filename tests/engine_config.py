"""The engine's configuration at the product's defaults, for tests (issue 39: the engine's configuration
objects have no defaults of their own; a test builds them from ``Settings`` so it tests the service that
runs, and where it deliberately differs it says why, with ``dataclasses.replace`` or a settings override)."""

from __future__ import annotations

from typing import Any

from service.core.config import CoreConfig, compensation_limits, core_config
from service.serve.policy import CompensationLimits
from service.settings import CompensationSettings, Settings


def product_core(**sections: Any) -> CoreConfig:
    """``core_config(Settings(**sections))``: the core's configuration at the product's defaults (and the
    ``CHTC_*`` environment), with the given sections (e.g. ``detector={"hold_s": 30.0}``)."""
    return core_config(Settings(**sections))


def product_limits(**compensation: Any) -> CompensationLimits:
    """The policy's limits at ``[compensation]``'s defaults with the given keys (validated)."""
    return compensation_limits(CompensationSettings(**compensation))


# the per-condition protocol with 10-min windows 10 and 20 min after a change: what the core's event tests
# were written for (the product's default is combined mode with a 7-min first window)
PER_CONDITION_10_20: dict[str, Any] = {
    "mode": "per_condition",
    "schedule_min": (10.0, 20.0),
    "min_window_s": 600.0,
}
