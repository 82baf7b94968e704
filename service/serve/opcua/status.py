"""The served-value policy's verdict as an OPC UA StatusCode (docs/integration.md, "StatusCodes").

A PLC's read blocks hide the quality, so the address space also carries ``Status.Usable``; but every value has
the StatusCode its verdict maps to, so that a client that does look (a SCADA, a historian) sees the same thing
REST says. One pure function over the typed verdict (never a reason string):

==============================================  ==========================================  ===========
verdict (status / reason)                       StatusCode                                  hex
==============================================  ==========================================  ===========
fresh and usable                                Good                                        0x00000000
no-data (no sample yet)                         Bad_WaitingForInitialData                   0x80320000
stale: data lost (``stale``, ``core_behind``)   Uncertain_NoCommunicationLastUsableValue    0x408F0000
  ... lost for longer than ``bad_after_s``      Bad_NoCommunication                         0x80310000
predicted (DAQ lost, CAN alive: open loop)      Uncertain_SubNormal                         0x40950000
  ... open loop too long                        Bad_NoCommunication                         0x80310000
at-bound, ``at_bound``, ``not_identified``,     Uncertain_SensorNotAccurate                 0x40930000
  prior-dominated H, ``ci_too_wide``,
  ``no_reference``, ``mechanics_uncalibrated``,
  ``state_inconsistent``
identifying, and the other reasons a value is   Uncertain_LastUsableValue                   0x40900000
  held (``condition_changed``, ``map_old``,
  ``speed_not_visited``, ``restored``,
  ``state_converging``, ``identification_old``,
  ``no_identification``)
==============================================  ==========================================  ===========

Predicted maps to Uncertain_SubNormal: Part 8 defines it as "the value is derived from multiple values and
has less than the required number of Good values", which is the open-loop growth exactly (computed from
speed and torque without the temperatures); Uncertain_LastUsableValue would claim the value stopped
changing, which it does not.
"""

from __future__ import annotations

import enum
from datetime import datetime

from service.contracts.verdict import ChtcStatus, Reason, Verdict

__all__ = ["UaStatus", "lost_since", "severity", "status_of", "worst"]


class UaStatus(enum.IntEnum):
    """The StatusCodes this server uses (OPC 10000-4, Part 6 table; SPEC §7)."""

    GOOD = 0x00000000
    UNCERTAIN_LAST_USABLE_VALUE = 0x40900000
    UNCERTAIN_SENSOR_NOT_ACCURATE = 0x40930000
    UNCERTAIN_SUB_NORMAL = 0x40950000
    UNCERTAIN_NO_COMMUNICATION_LAST_USABLE_VALUE = 0x408F0000
    BAD_NO_COMMUNICATION = 0x80310000
    BAD_WAITING_FOR_INITIAL_DATA = 0x80320000


_LOST = frozenset({Reason.STALE, Reason.CORE_BEHIND})
_NOT_ACCURATE = frozenset(
    {
        Reason.AT_BOUND,
        Reason.NOT_IDENTIFIED,
        Reason.CI_TOO_WIDE,
        Reason.NO_REFERENCE,
        Reason.MECHANICS_UNCALIBRATED,
        Reason.NO_OFFSET_BASELINE,
        Reason.STATE_INCONSISTENT,
    }
)


def status_of(verdict: Verdict, *, lost_s: float, bad_after_s: float) -> UaStatus:
    """The StatusCode of a value judged ``verdict`` (the table in the module docstring). ``lost_s``: how long
    the data have been lost [s] (``lost_since``), compared with ``bad_after_s`` for a lost-data verdict."""
    if verdict.status is ChtcStatus.NO_DATA or verdict.reason is Reason.NO_DATA:
        return UaStatus.BAD_WAITING_FOR_INITIAL_DATA
    if verdict.reason is Reason.OPEN_LOOP_TOO_LONG:
        return UaStatus.BAD_NO_COMMUNICATION
    if verdict.reason in _LOST:
        if lost_s > bad_after_s:
            return UaStatus.BAD_NO_COMMUNICATION
        return UaStatus.UNCERTAIN_NO_COMMUNICATION_LAST_USABLE_VALUE
    if verdict.status is ChtcStatus.PREDICTED:
        return UaStatus.UNCERTAIN_SUB_NORMAL
    if verdict.status is ChtcStatus.AT_BOUND or verdict.reason in _NOT_ACCURATE:
        return UaStatus.UNCERTAIN_SENSOR_NOT_ACCURATE
    if verdict.usable and verdict.status is ChtcStatus.FRESH:
        return UaStatus.GOOD
    return UaStatus.UNCERTAIN_LAST_USABLE_VALUE


def severity(code: UaStatus) -> int:
    """Good 0 < Uncertain 1 < Bad 2 (the two top bits)."""
    return {0: 0, 1: 1}.get(int(code) >> 30, 2)


def worst(*codes: UaStatus) -> UaStatus:
    """The most severe of ``codes`` (the first of equal severity)."""
    return max(codes, key=severity)


def lost_since(*times: datetime | None, now: datetime) -> float:
    """Seconds since the oldest of ``times`` [s] (None counts as never: infinite); 0 without any."""
    if not times:
        return 0.0
    if any(t is None for t in times):
        return float("inf")
    return max(0.0, max((now - t).total_seconds() for t in times if t is not None))
