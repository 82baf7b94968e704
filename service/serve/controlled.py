"""The served verdict with the CI gate, and the command value, advanced together on one clock (pure, but for
the small thread-safe holder ``Controller``; docs/design/policy.md, "A steady verdict" and "The command
value").

``step_control`` takes the policy's plain verdict (``service.serve.policy.compensation_verdict``: ``usable``
and its typed ``reason``), the served growth and its 95 % CI half-width, and returns the next
:class:`ControlState` and whether the growth is usable *with the gate*:

- the safety reasons (anything but ``ci_too_wide``) act at once: not usable whatever the gate says;
- the CI reason goes through ``service.serve.cigate.step_gate`` (hysteresis), stepped on every call;
- the command value (``service.serve.command.advance``) follows the gated verdict; its best estimate when not
  usable is the growth's mean when only the CI bars it, or the open-loop prediction (status ``predicted``)
  while the DAQ is lost; None (towards 0) otherwise.

The service and the compensation bench (``python -m benchmarks compensation``) call this same function.
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass, replace

import numpy as np

from service.contracts.command import CommandSnapshot
from service.contracts.verdict import Reason, Verdict
from service.estimate.growth import plc_compensation
from service.serve.cigate import CiGateLimits, CiGateState, step_gate
from service.serve.command import CommandState, CommandStatus, ControllerProfile, advance

__all__ = [
    "CommandSnapshot",
    "ControlLimits",
    "ControlState",
    "Controller",
    "best_estimate",
    "gated_verdict",
    "step_control",
]

CI_TOO_WIDE = "ci_too_wide"
PREDICTED = "predicted"


@dataclass(frozen=True, kw_only=True)
class ControlLimits:
    """The gate's limits, the controller's profile and the command's hold (``[compensation]`` ``ci_*`` and
    ``[controller]``; built by the engine's config from the settings, no defaults here)."""

    gate: CiGateLimits
    profile: ControllerProfile
    hold_s: float


@dataclass(frozen=True, kw_only=True)
class ControlState:
    """The CI gate's state and the command's (checkpointed with the live state)."""

    gate: CiGateState
    command: CommandState

    @classmethod
    def start(cls, t: float) -> ControlState:
        """The gate closed, the command at 0 (nothing applied yet)."""
        return cls(gate=CiGateState(), command=CommandState.start(t))

    def to_array(self) -> np.ndarray:
        """The state as 8 numbers (NaN for None), for the live checkpoint (``LiveCheckpoint.control``)."""

        def num(x: float | None) -> float:
            return math.nan if x is None else float(x)

        g, c = self.gate, self.command
        return np.array(
            [
                1.0 if g.open else 0.0,
                num(g.above_since),
                num(g.t),
                c.value_um,
                c.t,
                float(_STATUSES.index(c.status)),
                num(c.last_usable_t),
                c.target_um,
            ]
        )

    @classmethod
    def from_array(cls, arr: np.ndarray | None) -> ControlState | None:
        """``to_array``'s inverse; None for None or an array that is not one (an older checkpoint)."""
        if arr is None or np.shape(arr) != (8,):
            return None
        a = [float(x) for x in arr]

        def opt(x: float) -> float | None:
            return None if math.isnan(x) else x

        k = int(a[5]) if math.isfinite(a[5]) else -1
        if not (0 <= k < len(_STATUSES)) or not all(math.isfinite(a[i]) for i in (3, 4, 7)):
            return None
        gate = CiGateState(open=a[0] > 0.5, above_since=opt(a[1]), t=opt(a[2]))
        command = CommandState(
            value_um=a[3], t=a[4], status=_STATUSES[k], last_usable_t=opt(a[6]), target_um=a[7]
        )
        return cls(gate=gate, command=command)


_STATUSES = tuple(CommandStatus)


def best_estimate(*, safe: bool, status: str, growth_um: float | None) -> float | None:
    """What the command moves towards when the growth is not usable: the growth's mean when only its CI
    bars it (``safe``: the plain verdict usable or ``ci_too_wide``), the open-loop prediction while the DAQ is
    lost (``status`` ``predicted``); None when nothing is known."""
    if growth_um is None or not math.isfinite(growth_um):
        return None
    return growth_um if safe or status == PREDICTED else None


def step_control(
    state: ControlState,
    *,
    t: float,
    usable: bool,
    reason: str | None,
    status: str,
    growth_um: float | None,
    half_um: float,
    limits: ControlLimits,
) -> tuple[ControlState, bool]:
    """The gated verdict and the command at ``t`` [POSIX s] (module docstring). ``usable``/``reason``: the
    policy's plain verdict (``reason`` its code, None when usable); ``status``: the served status value;
    ``growth_um``: the served growth (None: nothing served); ``half_um``: its 95 % CI half-width (NaN: none).
    A ``t`` before the state's is taken as the state's (a clock that stepped back moves nothing)."""
    now = max(float(t), state.command.t)
    safe = usable or reason == CI_TOO_WIDE
    half = half_um if growth_um is not None else math.nan
    # open loop (DAQ lost) the CI only grows: no hold on the way out, it closes once above the tolerance
    gl = replace(limits.gate, exit_hold_s=0.0) if status == PREDICTED else limits.gate
    gate = step_gate(state.gate, t=now, half_um=half, limits=gl)
    gated = bool(safe and gate.open and growth_um is not None)
    best = best_estimate(safe=safe, status=status, growth_um=growth_um)
    command = advance(
        state.command,
        t=now,
        usable=gated,
        growth_um=growth_um if gated else None,
        best_um=best,
        profile=limits.profile,
        hold_s=limits.hold_s,
    )
    return ControlState(gate=gate, command=command), gated


# ----------------------------------------------------------------------------- the service's controller


class Controller:
    """The gate's and the command's state of one spindle, advanced by ``step`` on the service's clock (each
    published sample and each read; thread-safe). ``state`` is what the live checkpoint stores."""

    def __init__(
        self, limits: ControlLimits, *, tool_dir: int = -1, state: ControlState | None = None
    ) -> None:
        self.limits = limits
        self.tool_dir = tool_dir
        self._state = state
        self._lock = threading.Lock()

    @property
    def state(self) -> ControlState | None:
        """The state now (None: never stepped)."""
        with self._lock:
            return self._state

    def restore(self, state: ControlState | None) -> None:
        """Resume from a checkpointed state (None: start afresh)."""
        with self._lock:
            self._state = state

    def step(
        self, t: float, verdict: Verdict, *, growth_um: float | None, half_um: float
    ) -> tuple[Verdict, CommandSnapshot]:
        """The verdict with the CI gate and the command at ``t`` [POSIX s] from the policy's plain ``verdict``
        (module docstring)."""
        with self._lock:
            state = self._state if self._state is not None else ControlState.start(t)
            state, usable = step_control(
                state,
                t=t,
                usable=verdict.usable,
                reason=None if verdict.reason is None else verdict.reason.value,
                status=verdict.status.value,
                growth_um=growth_um,
                half_um=half_um,
                limits=self.limits,
            )
            self._state = state
        cmd = state.command
        snap = CommandSnapshot(
            value_um=cmd.value_um,
            status=cmd.status,
            profile=self.limits.profile,
            hold_s=self.limits.hold_s,
            plc=plc_compensation(cmd.value_um, tool_dir=self.tool_dir),
            at=cmd.t,
        )
        return gated_verdict(verdict, usable=usable, half_um=half_um, limits=self.limits.gate), snap


def gated_verdict(verdict: Verdict, *, usable: bool, half_um: float, limits: CiGateLimits) -> Verdict:
    """The policy's ``verdict`` with the gate's answer on the CI: a safety reason is kept as it is; a CI
    within the tolerance while the gate is still closed reads ``ci_too_wide`` (waiting for the entry level);
    a CI above the tolerance while the gate holds it open reads usable."""
    if usable == verdict.usable:
        return verdict
    if usable:
        return Verdict(verdict.status, True)
    entry = limits.enter_fraction * limits.max_ci95_um
    return Verdict(
        verdict.status,
        False,
        Reason.CI_TOO_WIDE,
        f"95 % CI half-width {half_um:.2f} µm: usable again at {entry:.2f} µm or less "
        "(compensation.ci_enter_fraction × max_ci95_um)",
    )
