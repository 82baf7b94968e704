"""The one served-value policy: whether a consumer may act on what the service serves now (pure functions).

A compensation controller acts on ``usable`` alone. This module is the only place that decides it, for every
outlet (``/chtc``, ``/compensation``, ``/chtc/map``, the metrics, the dashboard; OPC UA and MQTT later). Each
verdict is a :class:`Verdict`: the served value's ``status``, ``usable``, and when not usable a typed
:class:`Reason` with a human ``detail`` and the operator's ``action``. Nothing downstream parses strings.

What each served value needs (docs/design/policy.md):

- **the compensation** (the growth at the tool, from the live field): fresh data, or the DAQ down while CAN
  speed/torque keep coming (``predicted``, open loop, for at most ``max_open_loop_min``); the live state
  converged and consistent (NIS); a compensation reference; the H in use identified not longer ago than
  ``max_identification_age_min``; the growth's 95 % CI half-width within ``max_ci95_um``. A condition change
  does not blank it: the filter tracks the field through changes, and the CI carries the H error.
- **the H** (``/chtc``): fresh data, a converged live state, identified at the current, stable condition (or
  the speed map's H at the current speed), none on a bound of the search box, and each H either identified or
  prior-dominated (its band is the prior's: finite and honest), not the stored ones before a
  re-identification.

The inputs are the core's published view (``service.core.view.CoreView`` satisfies :class:`PolicyView`)
and the instant; the growth's CI half-width and the reference come from the growth server.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from datetime import datetime
from typing import TYPE_CHECKING, Protocol

import numpy as np

from service.contracts.snapshots import ConditionSnapshot, ConditionState
from service.contracts.verdict import Blocker, ChtcStatus, DataCode, DataProblem, Reason, Verdict

if TYPE_CHECKING:
    from service.settings import CompensationSettings

__all__ = [
    "CompensationLimits",
    "PolicyView",
    "chtc_verdict",
    "compensation_limits",
    "compensation_verdict",
    "data_verdict",
    "map_verdict",
]


@dataclass(frozen=True, kw_only=True)
class CompensationLimits:
    """The settings ``[compensation]`` (docs/configuration.md; no defaults here:
    ``service.core.config.compensation_limits`` builds it)."""

    max_ci95_um: float  # the growth's 95 % CI half-width the controller tolerates [µm]
    max_identification_age_min: float  # the H in use identified at most this long ago [min]
    max_open_loop_min: float  # DAQ down, CAN alive: usable open loop for at most this long [min]
    # not usable before a commissioning of the mechanics (``mechanics_uncalibrated``; docs/design/policy.md)
    require_mechanics_calibration: bool
    # not usable while the sensors' offsets are unknown (``no_offset_baseline``: calibration on, no baseline;
    # issue 40; docs/design/policy.md)
    require_offset_baseline: bool


def compensation_limits(section: CompensationSettings) -> CompensationLimits:
    """The policy's limits from ``[compensation]`` (the one mapping: the engine's config and the growth
    server's default both call it)."""
    return CompensationLimits(
        max_ci95_um=section.max_ci95_um,
        max_identification_age_min=section.max_identification_age_min,
        max_open_loop_min=section.max_open_loop_min,
        require_mechanics_calibration=section.require_mechanics_calibration,
        require_offset_baseline=section.require_offset_baseline,
    )


class LiveLike(Protocol):
    """What the policy reads of the live state (``service.estimate.state.FilterView``)."""

    @property
    def converged(self) -> bool: ...

    @property
    def started_at(self) -> float: ...

    def inconsistent(self, t: float) -> bool: ...


class NewestLike(Protocol):
    """What the policy reads of the newest sample (``service.core.view.NewestSample``)."""

    @property
    def t(self) -> datetime: ...

    @property
    def daq_ok(self) -> bool: ...

    @property
    def can_ok(self) -> bool: ...


class PolicyView(Protocol):
    """What the policy reads of the core's published view (``service.core.view.CoreView``)."""

    @property
    def newest(self) -> NewestLike | None: ...

    @property
    def live(self) -> LiveLike | None: ...

    @property
    def last_good_daq_t(self) -> datetime | None: ...

    def data_problems(self, now: datetime) -> tuple[DataProblem, ...]: ...


def _iso(t: datetime) -> str:
    return t.isoformat(timespec="seconds")


def data_verdict(
    problems: Sequence[DataProblem],
    *,
    has_sample: bool,
    last_good_daq_t: datetime | None,
    now: datetime,
    open_loop_limit_s: float | None,
) -> Verdict | None:
    """The data's part of every verdict (None: the data are fresh).

    ``no_data`` without a sample; ``core_behind`` (status ``stale``) when the core has not handled the
    samples acquired for longer than its limit (what is published trails what was acquired); ``stale`` when
    samples stopped or CAN is silent (the inputs of the live state are unknown); with the DAQ alone down
    (``daq_no_good_data``) and ``open_loop_limit_s`` given (the compensation), ``predicted``: usable so far
    (the caller checks the CI), or ``open_loop_too_long`` past the limit; without ``open_loop_limit_s``
    (the H, which need measured temperatures), ``stale``."""
    if not has_sample:
        return Verdict(ChtcStatus.NO_DATA, False, Reason.NO_DATA, "no sample acquired yet")
    if not problems:
        return None
    codes = {p.code for p in problems}
    detail = ", ".join(str(p) for p in problems) + " (see /readyz)"
    if DataCode.CORE_BEHIND in codes:  # what is published trails what was acquired: never fresh
        return Verdict(ChtcStatus.STALE, False, Reason.CORE_BEHIND, detail)
    if codes != {DataCode.DAQ_NO_GOOD_DATA} or open_loop_limit_s is None:
        return Verdict(ChtcStatus.STALE, False, Reason.STALE, detail)
    if last_good_daq_t is None:
        return Verdict(ChtcStatus.STALE, False, Reason.STALE, detail)
    open_s = max(0.0, (now - last_good_daq_t).total_seconds())
    if open_s > open_loop_limit_s:
        return Verdict(
            ChtcStatus.PREDICTED,
            False,
            Reason.OPEN_LOOP_TOO_LONG,
            f"no temperatures since {_iso(last_good_daq_t)} ({open_s / 60:.1f} min, limit "
            f"{open_loop_limit_s / 60:.0f} min); the growth is predicted from speed and torque",
        )
    return Verdict(ChtcStatus.PREDICTED, True)


def _live_verdict(live: LiveLike | None, now: datetime) -> Verdict | None:
    if live is None:
        not_started = "the live state has not started"
        return Verdict(ChtcStatus.CONVERGING, False, Reason.STATE_CONVERGING, not_started)
    if not live.converged:
        since = _iso(datetime.fromtimestamp(live.started_at, tz=now.tzinfo))
        return Verdict(
            ChtcStatus.CONVERGING,
            False,
            Reason.STATE_CONVERGING,
            f"the live temperature state has not converged since {since} (restart or data gap)",
        )
    if live.inconsistent(now.timestamp()):
        return Verdict(
            ChtcStatus.STALE,
            False,
            Reason.STATE_INCONSISTENT,
            "the live state's NIS has stayed above its band: the model and the data disagree",
        )
    return None


def compensation_verdict(
    view: PolicyView,
    now: datetime,
    *,
    limits: CompensationLimits,
    has_sample: bool,
    ci95_half_um: float,
    identified_at: datetime | None,
    has_reference: bool = True,
    has_mechanics: bool = True,
    has_offset_baseline: bool = True,
) -> Verdict:
    """Whether a controller may apply the growth served now (see the module docstring), in this order:
    data (``no_data``, ``stale``, ``open_loop_too_long``; ``stale`` at once when the newest sample has neither
    DAQ nor CAN data), live state (``state_converging``,
    ``state_inconsistent``), ``no_reference``, ``mechanics_uncalibrated`` (only when ``limits`` require a
    commissioning and ``has_mechanics`` is false), ``no_offset_baseline`` (only when ``limits`` require a
    baseline and ``has_offset_baseline`` is false), ``no_identification`` or ``identification_old``,
    ``ci_too_wide`` (not judged while the data or the live state block). The first is the verdict's
    ``reason``; every one that blocks is listed, in this order, in ``Verdict.blocking``. The status is
    ``fresh``, ``predicted`` (DAQ down, CAN alive: open loop), ``converging`` (the live state settles),
    ``stale`` or ``no-data``."""
    open_loop_s = 60.0 * limits.max_open_loop_min
    data = data_verdict(
        view.data_problems(now),
        has_sample=has_sample,
        last_good_daq_t=view.last_good_daq_t,
        now=now,
        open_loop_limit_s=open_loop_s,
    )
    status = ChtcStatus.FRESH if data is None else data.status
    newest = view.newest
    good_daq = view.last_good_daq_t
    if data is None and newest is not None and (good_daq is None or newest.t > good_daq):
        # the newest sample had too few usable temperatures: the live state runs open loop from that sample
        # on, before the freshness limit flags the DAQ (never served as fresh)
        early = DataProblem(DataCode.DAQ_NO_GOOD_DATA, "the newest sample has too few usable temperatures")
        data = data_verdict(
            (early,), has_sample=True, last_good_daq_t=good_daq, now=now, open_loop_limit_s=open_loop_s
        )
        status = ChtcStatus.STALE if data is None else data.status
    if (
        status in (ChtcStatus.FRESH, ChtcStatus.PREDICTED)
        and newest is not None
        and not newest.can_ok
        and (status is ChtcStatus.PREDICTED or not newest.daq_ok)
    ):
        # no temperatures and no speed/torque: nothing to predict from, stale at once (not after the
        # freshness limit, which the data problems wait for)
        return Verdict(
            ChtcStatus.STALE,
            False,
            Reason.STALE,
            "neither temperatures (DAQ) nor speed/torque (CAN) in the newest sample (see /readyz)",
        )
    found: list[Verdict] = []  # every blocking reason, in order
    if data is not None and not data.usable:
        found.append(data)
    live = _live_verdict(view.live, now)
    if live is not None:
        first = status if status is ChtcStatus.PREDICTED else live.status
        found.append(Verdict(first if not found else live.status, False, live.reason, live.detail))
    transient = bool(found)  # the data or the live state: the growth's CI means nothing then
    if not has_reference:
        no_zero = "no compensation reference (zero) is stored"
        found.append(Verdict(status, False, Reason.NO_REFERENCE, no_zero))
    if limits.require_mechanics_calibration and not has_mechanics:
        found.append(
            Verdict(
                status,
                False,
                Reason.MECHANICS_UNCALIBRATED,
                "the mechanics (mount restraint, α) are not commissioned: the growth's CI does not cover an "
                "unknown mount (compensation.require_mechanics_calibration)",
            )
        )
    if limits.require_offset_baseline and not has_offset_baseline:
        found.append(
            Verdict(
                status,
                False,
                Reason.NO_OFFSET_BASELINE,
                "no offset baseline of the sensors yet (a start on a warm spindle without the stored "
                "calibration, and no commissioning's that fits the sensors, or its 10-min check against "
                "the live residuals still running): the unknown offsets bend the field and the H, and the "
                "growth's CI does not cover that; let the spindle rest "
                "(compensation.require_offset_baseline)",
            )
        )
    found += _identification_blockers(
        status, now, identified_at, None if transient else ci95_half_um, limits=limits
    )
    if not found:
        return Verdict(status, True)
    head = found[0]
    more = tuple(Blocker(v.reason, v.detail) for v in found[1:] if v.reason is not None)
    return Verdict(head.status, False, head.reason, head.detail, more=more)


def _identification_blockers(
    status: ChtcStatus,
    now: datetime,
    identified_at: datetime | None,
    ci95_half_um: float | None,
    *,
    limits: CompensationLimits,
) -> list[Verdict]:
    """``no_identification`` or ``identification_old``; ``ci_too_wide`` (``ci95_half_um`` None: not
    judged)."""
    if identified_at is None:
        return [Verdict(status, False, Reason.NO_IDENTIFICATION, "no H identified yet")]
    out = []
    age_min = max(0.0, (now - identified_at).total_seconds()) / 60.0
    if age_min > limits.max_identification_age_min:
        out.append(
            Verdict(
                status,
                False,
                Reason.IDENTIFICATION_OLD,
                f"the H in use were identified {age_min:.0f} min ago "
                f"(limit {limits.max_identification_age_min:.0f} min)",
            )
        )
    if ci95_half_um is not None and (not np.isfinite(ci95_half_um) or ci95_half_um > limits.max_ci95_um):
        out.append(
            Verdict(
                status,
                False,
                Reason.CI_TOO_WIDE,
                f"95 % CI half-width {ci95_half_um:.2f} µm over the tolerance {limits.max_ci95_um:.2f} µm",
            )
        )
    return out


def chtc_verdict(
    *,
    has_sample: bool,
    problems: Sequence[DataProblem],
    live: LiveLike | None,
    now: datetime,
    condition: ConditionSnapshot | None,
    record_condition_id: int,
    map_verdict: Verdict | None,
    running: bool,
    bound: Sequence[bool],
    identified: Sequence[bool],
    prior_dominated: Sequence[bool],
    h: Sequence[float],
    restored: bool,
    zones: Sequence[str],
) -> Verdict:
    """Whether the H served now may be used by a model that needs them (``/chtc``), and their status.

    The status: with the speed map serving (``map_verdict``), the map's; otherwise ``no-data`` (no sample;
    ``stale`` for a restored record), ``stale`` (data not fresh), ``converging`` (fresh data, the live state
    not converged yet), ``stale`` (a restored record), ``identifying`` (a job runs, or the record is of
    another condition, or the condition is changing), else ``fresh``; a ``fresh`` one with an H on a bound of
    the search box is ``at-bound``.

    The reason, in order: ``no_data``, ``stale`` (the H need measured temperatures: no open loop),
    ``state_converging``, the map's own (``map_old``, ``speed_not_visited``, ``restored``),
    ``condition_changed``, ``at_bound``, ``not_identified`` (an H neither identified nor prior-dominated, or
    not a positive number), ``restored``. A job running at the held condition leaves the H usable."""
    converging = live is not None and not live.converged
    if map_verdict is not None:
        status = map_verdict.status
    elif not has_sample:
        status = ChtcStatus.STALE if restored else ChtcStatus.NO_DATA
    elif problems:
        status = ChtcStatus.STALE
    elif converging:  # fresh data: the live state settles (the H served are the last identified ones)
        status = ChtcStatus.CONVERGING
    elif restored:
        status = ChtcStatus.STALE
    elif (
        running
        or condition is None
        or condition.id != record_condition_id
        or condition.state is not ConditionState.STABLE
    ):
        status = ChtcStatus.IDENTIFYING
    else:
        status = ChtcStatus.FRESH
    if status is ChtcStatus.FRESH and any(bound):
        status = ChtcStatus.AT_BOUND
    data = data_verdict(
        problems, has_sample=has_sample, last_good_daq_t=None, now=now, open_loop_limit_s=None
    )
    if data is not None:
        return Verdict(status, False, data.reason, data.detail)
    if converging:
        assert live is not None
        since = _iso(datetime.fromtimestamp(live.started_at, tz=now.tzinfo))
        return Verdict(
            status,
            False,
            Reason.STATE_CONVERGING,
            f"the live temperature state has not converged since {since} (restart or data gap): no "
            "identification window starts before it has, the H are the last identified ones",
        )
    if map_verdict is not None and not map_verdict.usable:
        return Verdict(status, False, map_verdict.reason, map_verdict.detail)
    if (
        condition is None
        or condition.id != record_condition_id
        or condition.state is not ConditionState.STABLE
    ):
        now_c = "none" if condition is None else f"{condition.id} ({condition.state.value})"
        return Verdict(
            status,
            False,
            Reason.CONDITION_CHANGED,
            f"identified at condition {record_condition_id}, now {now_c}",
        )
    if any(bound):
        names = ", ".join(n for n, b in zip(zones, bound, strict=True) if b)
        return Verdict(
            status, False, Reason.AT_BOUND, f"{names} on a bound of the search box (not identified)"
        )
    weak = [n for n, ok, p in zip(zones, identified, prior_dominated, strict=True) if not (ok or p)]
    positive = len(h) == len(zones) and all(np.isfinite(float(x)) and x > 0 for x in h)
    if weak or not positive:
        return Verdict(
            status,
            False,
            Reason.NOT_IDENTIFIED,
            f"{', '.join(weak) or 'H'} (95 % CI too wide, no prior holds it)",
        )
    if restored:
        return Verdict(
            status, False, Reason.RESTORED, "the last stored H, not re-identified since the restart"
        )
    return Verdict(status, True)


class MapLike(Protocol):
    """What ``map_verdict`` reads of the speed map (``service.identify.speedmap.SpeedMap``)."""

    @property
    def restored(self) -> bool: ...

    @property
    def fitted_at(self) -> datetime: ...

    def covered(self, speed_rpm: float, *, margin_rpm: float, min_visit_s: float) -> bool: ...


def map_verdict(
    speed_map: MapLike,
    *,
    newest_t: datetime | None,
    speed_rpm: float | None,
    problems: Sequence[DataProblem],
    converging_since: datetime | None,
    fresh_s: float,
    margin_rpm: float,
    min_visit_s: float,
) -> Verdict:
    """How current the speed map is at the current speed. In this order: ``no-data`` (no sample), ``stale``
    (``problems``; or no speed known at all: ``speed_rpm`` None with a sample; or ``restored``: the stored
    map, not re-fitted since the restart), ``converging`` (``state_converging``), then ``identifying`` with
    ``map_old`` (the fit's window ended more than ``fresh_s`` before the newest sample) or
    ``speed_not_visited`` (the current speed is not within ``margin_rpm`` of a speed with >= ``min_visit_s``
    of fitted data), else ``fresh``."""
    stale = ChtcStatus.STALE
    if newest_t is None:
        if speed_map.restored:
            return Verdict(stale, False, Reason.RESTORED, "the stored map, no sample since the restart")
        return Verdict(ChtcStatus.NO_DATA, False, Reason.NO_DATA, "no sample acquired yet")
    if problems:
        return Verdict(stale, False, Reason.STALE, ", ".join(str(p) for p in problems) + " (see /readyz)")
    if speed_rpm is None:
        return Verdict(stale, False, Reason.STALE, "no speed value known yet (see /readyz)")
    if speed_map.restored:
        return Verdict(stale, False, Reason.RESTORED, "the stored map, not re-fitted since the restart")
    if converging_since is not None:
        detail = f"the live temperature state has not converged since {_iso(converging_since)}"
        return Verdict(ChtcStatus.CONVERGING, False, Reason.STATE_CONVERGING, detail)
    age = (newest_t - speed_map.fitted_at).total_seconds()
    if age > fresh_s:
        return Verdict(
            ChtcStatus.IDENTIFYING,
            False,
            Reason.MAP_OLD,
            f"the map's data end {age / 60:.1f} min before the newest sample (limit {fresh_s / 60:.0f} min)",
        )
    if not speed_map.covered(speed_rpm, margin_rpm=margin_rpm, min_visit_s=min_visit_s):
        return Verdict(
            ChtcStatus.IDENTIFYING,
            False,
            Reason.SPEED_NOT_VISITED,
            f"{abs(speed_rpm):.0f} rpm is not within {margin_rpm:.0f} rpm of a speed with "
            f">= {min_visit_s:.0f} s of fitted data",
        )
    return Verdict(ChtcStatus.FRESH, True)
