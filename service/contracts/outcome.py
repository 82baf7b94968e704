"""What became of an identification: the values stored in ``identifications.outcome`` and served as
``outcome`` by the API (pure; no model, no database).

A job the worker ran ends as ``OK``, ``FAILED``, ``INSUFFICIENT_DATA`` (too few usable data, found by the
window rules or by the identification itself) or ``CANCELLED``; a job the core did not start (spindle idle)
is ``SKIPPED``. ``service.identify.worker.job_outcome_of`` maps a job's exception to one of these.
"""

from __future__ import annotations

import enum

__all__ = ["OUTCOMES", "Outcome"]


class Outcome(enum.StrEnum):
    OK = "ok"
    FAILED = "failed"
    INSUFFICIENT_DATA = "insufficient-data"
    SKIPPED = "skipped"
    CANCELLED = "cancelled"


OUTCOMES: tuple[str, ...] = tuple(o.value for o in Outcome)
