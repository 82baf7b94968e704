"""The command value: what a controller applies now, and why it never jumps (pure; docs/design/policy.md,
"The command value").

The growth's verdict (``usable``) says when the growth may be applied. A controller that applies it while
usable and holds it when not makes a step each time the verdict comes back after a hold, and a step when the
first usable value arrives. The command value does that logic once, for every outlet:

- **following** the growth while the verdict is usable;
- **holding** the last applied value for ``hold_s`` after the verdict drops (a short drop — a CI that widens
  for a minute, a gap in the data — changes nothing at the tool);
- then **fading** towards the best estimate the service still has (``best_um``: the growth's mean when its
  CI is merely wide, the open-loop prediction when the DAQ is lost), or towards 0 when nothing is known
  (``none``), at the profile's rate;
- never moving by more than the controller profile allows: ``max_step_um`` per update, ``max_rate_um_s``,
  and within ``±limit_um`` (``at_limit``); a move that the step or rate cut is ``rate_limited``.

The state advances on the service's clock (``t``, POSIX s): a clock that steps back moves nothing.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

from service.contracts.command import CommandError, CommandStatus, ControllerProfile

__all__ = [
    "PROFILES",
    "CommandError",
    "CommandState",
    "CommandStatus",
    "ControllerProfile",
    "advance",
    "profile_from",
]


# sinumerik: SD43900 is spread over interpolation cycles (MD32760) and values above MD20392 (default 1 mm) are
# cut without an alarm; fanuc: the thermal-growth input (G178-G179) alarms on a step of 9 999 detection units
# (1 µm at IS-B) or more; heidenhain: older controls track the offset at 1 µm/s. The step and rate are far
# above a spindle's thermal growth rate (< 1 µm/min), so they bind only on a return after a hold.
PROFILES: dict[str, ControllerProfile] = {
    "generic": ControllerProfile(name="generic", max_step_um=1.0, max_rate_um_s=0.5, limit_um=200.0),
    "sinumerik": ControllerProfile(name="sinumerik", max_step_um=2.0, max_rate_um_s=1.0, limit_um=1000.0),
    "fanuc": ControllerProfile(name="fanuc", max_step_um=5.0, max_rate_um_s=1.0, limit_um=9998.0),
    "heidenhain": ControllerProfile(name="heidenhain", max_step_um=1.0, max_rate_um_s=1.0, limit_um=1000.0),
}


def profile_from(
    name: str,
    *,
    max_step_um: float | None = None,
    max_rate_um_s: float | None = None,
    limit_um: float | None = None,
) -> ControllerProfile:
    """The named profile with the given overrides (None: the profile's own)."""
    if name not in PROFILES:
        raise CommandError(f"controller.profile: {name!r} is not one of {', '.join(sorted(PROFILES))}")
    base = PROFILES[name]
    return replace(
        base,
        max_step_um=base.max_step_um if max_step_um is None else max_step_um,
        max_rate_um_s=base.max_rate_um_s if max_rate_um_s is None else max_rate_um_s,
        limit_um=base.limit_um if limit_um is None else limit_um,
    )


@dataclass(frozen=True, kw_only=True)
class CommandState:
    """The command value at ``t`` (POSIX s) and how it got there; ``last_usable_t``: when the growth was last
    usable (None: never since the start)."""

    value_um: float
    t: float
    status: CommandStatus
    last_usable_t: float | None = None
    target_um: float = 0.0  # where the command is heading

    @classmethod
    def start(cls, t: float) -> CommandState:
        """Nothing applied yet: 0 at ``t``."""
        return cls(value_um=0.0, t=float(t), status=CommandStatus.NONE)


def _target(
    state: CommandState,
    *,
    t: float,
    usable: bool,
    growth_um: float | None,
    best_um: float | None,
    hold_s: float,
) -> tuple[float, CommandStatus]:
    if usable and growth_um is not None:
        return growth_um, CommandStatus.FOLLOWING
    held = state.last_usable_t is not None and t - state.last_usable_t < hold_s
    if held and state.status is not CommandStatus.NONE:
        return state.value_um, CommandStatus.HOLDING
    if best_um is not None:
        return best_um, CommandStatus.FADING
    return 0.0, CommandStatus.NONE


def advance(
    state: CommandState,
    *,
    t: float,
    usable: bool,
    growth_um: float | None,
    best_um: float | None,
    profile: ControllerProfile,
    hold_s: float,
) -> CommandState:
    """The command at ``t`` from the one before (see the module docstring). ``growth_um``: the served growth
    (applied while ``usable``); ``best_um``: the best estimate when not usable (None: nothing known)."""
    for name, value in (("growth_um", growth_um), ("best_um", best_um)):
        if value is not None and not math.isfinite(value):
            raise CommandError(f"{name}: must be finite, got {value!r}")
    dt = max(0.0, float(t) - state.t)
    now = max(float(t), state.t)
    target, mode = _target(state, t=now, usable=usable, growth_um=growth_um, best_um=best_um, hold_s=hold_s)
    allowed = min(profile.max_step_um, profile.max_rate_um_s * dt)
    delta = target - state.value_um
    step = max(-allowed, min(allowed, delta))
    value = state.value_um + step
    status = mode
    if abs(delta - step) > 1e-9 and mode is CommandStatus.FOLLOWING:
        status = CommandStatus.RATE_LIMITED
    if abs(value) > profile.limit_um:
        value = math.copysign(profile.limit_um, value)
        status = CommandStatus.AT_LIMIT
    last_usable = now if (usable and growth_um is not None) else state.last_usable_t
    return CommandState(value_um=value, t=now, status=status, last_usable_t=last_usable, target_um=target)
