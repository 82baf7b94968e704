"""The pure part of ``python -m benchmarks opcua --spindles N``: percentiles, the phases' aggregation, and the
comparison of one spindle's OPC UA values with its REST ``/compensation`` answer at the same ``at``.

No I/O here: ``benchmarks.opcua_host`` (the shell) measures, this module turns what it measured into figures.
"""

from __future__ import annotations

import math
import statistics
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from datetime import datetime
from typing import Any

__all__ = [
    "COMPARED",
    "COMPENSATION_NODES",
    "UaValue",
    "differences",
    "median_or_none",
    "percentile",
    "rest_ratio",
    "spread",
]

# the 10 compensation variables one client reads in one Read (the single-spindle and the hosted bench)
COMPENSATION_NODES = (
    "Status.Usable",
    "Status.Heartbeat",
    "Status.SampleAge",
    "Growth.Axial",
    "Growth.AxialCiLow95",
    "Growth.AxialCiHigh95",
    "Controller.CorrectionUm",
    "Controller.SD43900Mm",
    "Controller.SD42960Mm",
    "Controller.IsgOffset0p1um",
)

# the OPC UA variables compared with GET /api/v1/spindles/{id}/compensation: the values whose
# SourceTimestamp is the growth's ``at`` and whose StatusCode is the verdict's
COMPARED = ("Growth.Axial", "Growth.AxialCiLow95", "Controller.SD43900Mm", "Controller.IsgOffset0p1um")
STATUS_NODES = ("Status.Text", "Status.Usable", "Status.Reason", "Status.Code")


@dataclass(frozen=True)
class UaValue:
    """One DataValue as a client reads it: its value (None when the server sent none), StatusCode (int)
    and SourceTimestamp (UTC, or None)."""

    value: Any
    status: int
    source_time: datetime | None


def percentile(xs: Sequence[float], q: float) -> float | None:
    """The q-th percentile (0-100, linear between order statistics, as numpy's default); None when empty."""
    if not xs:
        return None
    s = sorted(xs)
    rank = (len(s) - 1) * q / 100.0
    lo = math.floor(rank)
    hi = min(lo + 1, len(s) - 1)
    return s[lo] + (s[hi] - s[lo]) * (rank - lo)


def median_or_none(xs: Iterable[float | None]) -> float | None:
    """The median of the values that were measured; None when none were."""
    vals = [x for x in xs if x is not None]
    return statistics.median(vals) if vals else None


def rest_ratio(on_p99_ms: Iterable[float | None], off_p99_ms: Iterable[float | None]) -> float | None:
    """REST p99 with the outlets on / off: the median of each phase's p99 over its repeats, then the ratio."""
    on, off = median_or_none(on_p99_ms), median_or_none(off_p99_ms)
    if on is None or off is None or off <= 0:
        return None
    return on / off


def spread(i: int, k: int, n: int) -> int:
    """Which of ``n`` spindles client ``k``'s ``i``-th read goes to: every client walks all spindles, the
    clients one spindle apart, so each instant's reads cover ``min(clients, n)`` spindles."""
    return (i + k) % n


def differences(rest: Mapping[str, Any], ua_values: Mapping[str, UaValue]) -> list[str]:
    """What differs between one spindle's REST ``/compensation`` body and its OPC UA values read at the same
    ``at``; empty when they agree. Agreeing: ``Status.Text``, ``Status.Usable``, ``Status.Reason`` are REST's
    status, usable flag and reason code; every compared value has REST's ``at`` as SourceTimestamp and the
    StatusCode ``Status.Code`` says; that StatusCode is what the verdict maps to (``status_of``; a lost-data
    verdict may be either of its two codes, which depend on how long the data have been lost); and, unless
    Bad (a client drops a Bad value), the axial growth and the controller's integer offset are REST's."""
    from service.contracts.verdict import ChtcStatus, Reason, Verdict
    from service.serve.opcua.status import UaStatus, status_of

    out: list[str] = []
    want = {
        "Status.Text": rest["status"],
        "Status.Usable": bool(rest["usable_for_compensation"]),
        "Status.Reason": rest["reason_code"] or "",
    }
    for path, value in want.items():
        if ua_values[path].value != value:
            out.append(f"{path}: OPC UA {ua_values[path].value!r}, REST {value!r}")
    code = ua_values["Status.Code"].value
    reason = Reason(rest["reason_code"]) if rest["reason_code"] else None
    verdict = Verdict(ChtcStatus(rest["status"]), bool(rest["usable_for_compensation"]), reason)
    allowed = {status_of(verdict, lost_s=lost, bad_after_s=1.0) for lost in (0.0, 2.0)}
    if code not in {int(c) for c in allowed}:
        names = sorted(UaStatus(c).name for c in allowed)
        out.append(f"Status.Code: {code:#010x}, the verdict maps to {' or '.join(names)}")
    at = datetime.fromisoformat(str(rest["at"]).replace("Z", "+00:00"))
    for path in COMPARED:
        v = ua_values[path]
        if v.status != code:
            out.append(f"{path}: StatusCode {v.status:#010x}, Status.Code {code:#010x}")
        if v.source_time != at:
            out.append(f"{path}: SourceTimestamp {v.source_time}, REST at {at}")
    if code >> 30 != 2:
        if not _close(ua_values["Growth.Axial"].value, rest["axial"]["um"], 1e-3):
            out.append(f"Growth.Axial: OPC UA {ua_values['Growth.Axial'].value}, REST {rest['axial']['um']}")
        isg = rest["plc"]["isg_temp_comp_offset_0_0p1um"]
        if (got := ua_values["Controller.IsgOffset0p1um"].value) != isg:
            out.append(f"Controller.IsgOffset0p1um: OPC UA {got}, REST {isg}")
    return out


def _close(a: Any, b: Any, tol: float) -> bool:
    if a is None or b is None:
        return a is b
    return bool(abs(float(a) - float(b)) <= tol)
