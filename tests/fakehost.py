"""A host with no spindle running, as ``api.fleet`` reads one: the ``FleetHost`` protocol's fields in one
place, so a field the protocol gains is added here once (tests/api/test_api_fleet_*, tests/deploy)."""

from __future__ import annotations

from types import SimpleNamespace

from service.settings import Settings

__all__ = ["bare_host"]


def bare_host(clock: object = None) -> SimpleNamespace:
    """Default settings, no spindle, none failed, no outlet counters; ``clock`` as given."""
    return SimpleNamespace(settings=Settings(), clock=clock, spindles={}, failed={}, outlet_metrics=dict)
