"""The command value's vocabulary (issue 42; ``service.serve.command`` computes it, docs/design/policy.md
"The command value"): its status, the controller profile that bounds it, and the snapshot served with
``/compensation``."""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass

from service.contracts.growth import PlcCompensation
from service.errors import ServiceError

__all__ = ["CommandError", "CommandSnapshot", "CommandStatus", "ControllerProfile"]


class CommandError(ServiceError, ValueError):
    """A controller profile or command input that cannot be used (names the field)."""


class CommandStatus(enum.StrEnum):
    """What the command value does now (``/compensation`` ``command.status``)."""

    FOLLOWING = "following"  # equals the usable growth
    RATE_LIMITED = "rate_limited"  # moving towards its target, cut by the profile's step or rate
    HOLDING = "holding"  # the verdict dropped: the last applied value, held for hold_s
    FADING = "fading"  # past the hold: moving towards the best estimate the service has
    AT_LIMIT = "at_limit"  # clipped at the profile's absolute limit
    NONE = "none"  # nothing known: 0, or moving towards it


@dataclass(frozen=True, kw_only=True)
class ControllerProfile:
    """How far a controller lets the command move (``[controller]``; docs/design/policy.md says where each
    default comes from)."""

    name: str
    max_step_um: float  # the largest change between two updates [µm]
    max_rate_um_s: float  # the largest rate of change [µm/s]
    limit_um: float  # the largest magnitude served [µm]

    def __post_init__(self) -> None:
        for field in ("max_step_um", "max_rate_um_s", "limit_um"):
            value = getattr(self, field)
            if not (math.isfinite(value) and value > 0):
                raise CommandError(f"controller.{field}: must be a positive number, got {value!r}")


@dataclass(frozen=True, kw_only=True)
class CommandSnapshot:
    """The command value served with ``/compensation`` (``command``): ``value_um`` [µm] what the controller
    applies now (the axial growth it compensates, + towards the tool), its ``status``, the ``profile`` that
    bounds it, and ``plc``: the value in each controller's unit (``service.estimate.growth.plc_compensation``
    on the command value)."""

    value_um: float
    status: CommandStatus
    profile: ControllerProfile
    hold_s: float
    plc: PlcCompensation
    at: float  # the command's instant [POSIX s]
