"""The CI part of the compensation verdict, with hysteresis (pure; docs/design/policy.md, "A steady verdict").

A CI half-width that sits near the tolerance flips a plain threshold every few seconds. The gate opens when
the half-width is at most ``enter_fraction`` of the tolerance, and closes when it has stayed above the
tolerance for ``exit_hold_s``, or at once when it passes ``hard_fraction`` of the tolerance (or is not a
number): a CI far outside what the controller tolerates is never served as usable. Only the CI reason has
hysteresis; the safety reasons (no data, stale, no reference, uncalibrated mechanics, an inconsistent state)
act at once in ``service.serve.policy``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from service.errors import ServiceError

__all__ = ["CiGateError", "CiGateLimits", "CiGateState", "step_gate"]


class CiGateError(ServiceError, ValueError):
    """A gate setting out of range (names the setting)."""


@dataclass(frozen=True, kw_only=True)
class CiGateLimits:
    """``[compensation]`` ``max_ci95_um``, ``ci_enter_fraction``, ``ci_exit_hold_s``, ``ci_hard_fraction``."""

    max_ci95_um: float
    enter_fraction: float
    exit_hold_s: float
    hard_fraction: float

    def __post_init__(self) -> None:
        if not 0.0 < self.enter_fraction <= 1.0:
            raise CiGateError(f"compensation.ci_enter_fraction: must be in (0, 1], got {self.enter_fraction}")
        if not self.exit_hold_s >= 0.0:
            raise CiGateError(f"compensation.ci_exit_hold_s: must be >= 0, got {self.exit_hold_s}")
        if not self.hard_fraction >= 1.0:
            raise CiGateError(f"compensation.ci_hard_fraction: must be >= 1, got {self.hard_fraction}")


@dataclass(frozen=True, kw_only=True)
class CiGateState:
    """Whether the CI lets the growth be applied (``open``), since when it has been above the tolerance while
    open (``above_since``, POSIX s), and the instant of the last step (``t``)."""

    open: bool = False
    above_since: float | None = None
    t: float | None = None


def step_gate(state: CiGateState, *, t: float, half_um: float, limits: CiGateLimits) -> CiGateState:
    """The gate at ``t`` for the CI half-width ``half_um`` [µm]. A time before the last step (a clock that
    stepped back) restarts the above-tolerance timer from ``t``."""
    tol = limits.max_ci95_um
    if not math.isfinite(half_um) or half_um > limits.hard_fraction * tol:
        return CiGateState(open=False, above_since=None, t=t)
    if not state.open:
        return CiGateState(open=half_um <= limits.enter_fraction * tol, above_since=None, t=t)
    if half_um <= tol:
        return CiGateState(open=True, above_since=None, t=t)
    since = state.above_since
    if since is None or (state.t is not None and t < state.t):
        since = t
    if t - since >= limits.exit_hold_s:
        return CiGateState(open=False, above_since=None, t=t)
    return CiGateState(open=True, above_since=since, t=t)
