"""The typed verdict on a served value (``Verdict``, ``Reason``) and the freshness of H (``ChtcStatus``): the
vocabulary of the served-value policy (``service.serve.policy``), kept apart so that the snapshots
(``service.contracts.snapshots``) can carry a verdict without importing the policy's functions."""

from __future__ import annotations

import enum
from dataclasses import dataclass

__all__ = ["ACTIONS", "Blocker", "ChtcStatus", "DataCode", "DataProblem", "Reason", "Verdict"]


class ChtcStatus(enum.StrEnum):
    """Freshness of the values the API serves."""

    FRESH = "fresh"  # from recent good data (H: identified at the current, stable condition)
    PREDICTED = "predicted"  # the DAQ is down, CAN speed/torque alive: the live state runs open loop (growth)
    IDENTIFYING = "identifying"  # condition changed; a new identification is queued or running
    STALE = "stale"  # no recent good data (DAQ/CAN down, hung, frozen) or restored, not re-identified
    CONVERGING = "converging"  # fresh data, the live state settling after a (re)start or a gap
    AT_BOUND = "at-bound"  # identified at the current condition, but an H sits on a bound of the search box
    NO_DATA = "no-data"  # no samples at all


class Reason(enum.StrEnum):
    """Why a served value may not be used now (one code per verdict; ``detail`` says more)."""

    NO_DATA = "no_data"  # no sample acquired yet
    NO_IDENTIFICATION = "no_identification"  # no H yet (nothing identified, nothing stored)
    STALE = "stale"  # the data are not fresh (DAQ and CAN, or CAN alone, or acquisition stalled)
    STATE_CONVERGING = "state_converging"  # the live state has not converged since a (re)start or a gap
    STATE_INCONSISTENT = (
        "state_inconsistent"  # the live state's NIS is above its band: model and data disagree
    )
    CONDITION_CHANGED = "condition_changed"  # H identified at another condition, or the condition is changing
    MAP_OLD = "map_old"  # the speed map's data end too long before the newest sample
    SPEED_NOT_VISITED = "speed_not_visited"  # the speed map has no fitted data near the current speed
    AT_BOUND = "at_bound"  # an H on a bound of the search box
    NOT_IDENTIFIED = "not_identified"  # an H's CI too wide, and not held by a prior
    RESTORED = "restored"  # the last stored H, not re-identified since the restart
    IDENTIFICATION_OLD = "identification_old"  # the H in use were identified too long ago
    CI_TOO_WIDE = "ci_too_wide"  # the growth's 95 % CI half-width exceeds the tolerance
    NO_REFERENCE = "no_reference"  # no compensation reference (zero) stored
    OPEN_LOOP_TOO_LONG = "open_loop_too_long"  # DAQ down longer than the open-loop limit
    CORE_BEHIND = "core_behind"  # the core thread's backlog of samples is older than its limit
    MECHANICS_UNCALIBRATED = "mechanics_uncalibrated"  # no commissioning of the growth's mechanics yet
    NO_OFFSET_BASELINE = "no_offset_baseline"  # the sensors' offsets unknown (no baseline at rest yet)


ACTIONS: dict[Reason, str] = {
    Reason.NO_DATA: "Check that the DAQ and the CAN sensor are connected and the service acquires (/readyz).",
    Reason.NO_IDENTIFICATION: "Wait: the first identification runs once the spindle has run a few minutes.",
    Reason.STALE: "Check the devices named in the detail (/readyz); compensation resumes when data return.",
    Reason.STATE_CONVERGING: "Wait a few minutes: the live temperature state is settling after a (re)start.",
    Reason.STATE_INCONSISTENT: "Check the sensors (a moved or failing sensor?) and /readyz; it clears itself "
    "if the model and data agree again.",
    Reason.CONDITION_CHANGED: "Wait: the H are re-identified at the new condition.",
    Reason.MAP_OLD: "Run the spindle a while: the speed map is re-fitted from new data.",
    Reason.SPEED_NOT_VISITED: "Run at this speed for a few minutes so the map learns it.",
    Reason.AT_BOUND: "Check the sensors and the model's search box; re-identify (Identify now).",
    Reason.NOT_IDENTIFIED: "Run the spindle at varied speeds so the data can see every H.",
    Reason.RESTORED: "Wait: the stored H are re-identified after the restart.",
    Reason.IDENTIFICATION_OLD: "Re-identify (Identify now) or run the spindle so the H are refreshed.",
    Reason.CI_TOO_WIDE: "Wait for more data, or widen compensation.max_ci95_um if the machine allows.",
    Reason.NO_REFERENCE: "Set the compensation zero at rest (Set zero, or `chtc commission zero`).",
    Reason.OPEN_LOOP_TOO_LONG: "Restore the temperature DAQ: the prediction without it has run too long.",
    Reason.CORE_BEHIND: "Check the machine's CPU load: the service falls behind its samples; it catches up "
    "in order and clears itself (see /healthz, chtc_core_lag_seconds).",
    Reason.MECHANICS_UNCALIBRATED: "Commission the growth from a measured thermal test "
    "(`chtc commission growth`, docs/commissioning.md).",
    Reason.NO_OFFSET_BASELINE: "Let the spindle rest in equilibrium (the baseline is taken by itself) or "
    "take one at rest (POST /api/v1/sensors/baseline); a restart with the stored calibration keeps it.",
}


class DataCode(enum.StrEnum):
    """Why the acquired data are not fresh (``CoreView.data_problems``)."""

    NO_SAMPLE = "no_sample"  # acquisition stalled: no sample at all for too long
    DAQ_NO_GOOD_DATA = "daq_no_good_data"  # no sample with enough temperatures and the ambient
    CAN_NO_GOOD_DATA = "can_no_good_data"  # no speed/torque from CAN
    CORE_BEHIND = "core_behind"  # samples acquired but not yet handled by the core for too long


@dataclass(frozen=True)
class DataProblem:
    code: DataCode
    detail: str

    def __str__(self) -> str:
        return f"{self.code.value}: {self.detail}" if self.detail else self.code.value


@dataclass(frozen=True)
class Blocker:
    """One reason a served value may not be used, with its detail and the operator's action."""

    reason: Reason
    detail: str | None = None

    @property
    def action(self) -> str:
        return ACTIONS[self.reason]

    @property
    def text(self) -> str:
        return self.reason.value if not self.detail else f"{self.reason.value}: {self.detail}"


@dataclass(frozen=True)
class Verdict:
    """One served value's verdict at an instant: ``reason`` None iff ``usable``. ``reason`` and ``detail`` are
    the first blocking reason; ``more`` the others that block too, in the policy's order (a user who stores
    the zero then learns at once that the mechanics are uncommissioned, not after)."""

    status: ChtcStatus
    usable: bool
    reason: Reason | None = None
    detail: str | None = None
    more: tuple[Blocker, ...] = ()

    @property
    def action(self) -> str | None:
        """What the operator should do (None when usable)."""
        return None if self.reason is None else ACTIONS[self.reason]

    @property
    def blocking(self) -> tuple[Blocker, ...]:
        """Every reason that blocks, in order: the first (``reason``) and ``more`` (empty when usable)."""
        return () if self.reason is None else (Blocker(self.reason, self.detail), *self.more)

    @property
    def text(self) -> str | None:
        """``"code: detail"`` for logs and humans (never parsed)."""
        if self.reason is None:
            return None
        return self.reason.value if not self.detail else f"{self.reason.value}: {self.detail}"
