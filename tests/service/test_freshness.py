"""Freshness is the age of the newest GOOD data, not of the newest sample (issue 12, item 1).

The acquisition appends a sample every period whatever the devices do, so a service that looks only at the
newest sample's age stays `fresh`/ready with the DAQ unreachable, hung, answering garbage or frozen. Here the
service core is driven by the samples the real acquisition (``drivers.acquisition.combine``) builds from what
the drivers report in each failure, with an injected clock: `/chtc` must go `stale` and `/readyz` not ready
within ``stale_after_s`` of the last good sample, naming the reason, and `usable_for_compensation` false.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from datetime import UTC, datetime, timedelta
from typing import Any

import numpy as np
import pytest

from drivers.acquisition import combine
from drivers.can_codec import SensorStatus
from drivers.can_sensor import CanReading
from drivers.modbus_daq import DaqReading
from drivers.quality import Quality
from drivers.ringbuffer import Sample
from model.plant import Segment
from service.contracts.records import IdentificationData
from service.contracts.snapshots import ConditionSnapshot, ConditionState
from service.contracts.verdict import ChtcStatus
from service.core.machine import ServiceCore
from service.host.runtime import core_config
from service.identify.worker import JobOutcome, JobRequest, run_job
from service.shell.service import SoftSensorService
from tests.modes import per_condition

from .conftest import plant_run, samples_of

PERIOD_S = 10.0


@dataclass
class Rig:
    core: ServiceCore
    svc: SoftSensorService
    now: list[datetime]
    last: Sample

    def feed(self, sample: Sample) -> None:
        self.svc.on_sample(sample)  # a scheduled re-identification runs at once (run_job)
        self.now[0] = sample.t + timedelta(seconds=1)


@pytest.fixture(scope="module")
def identified(loaded_model):  # type: ignore[no-untyped-def]
    """Good samples of a 3000 rpm condition after 5 min idle, identified at 10 and 20 min: the config and
    the samples. Per-condition mode: these tests edit that protocol's identification (an H on a bound, CIs too
    wide) and its condition-change rule; the speed map's status rules: tests/service/test_speed_map.py."""
    cfg = core_config(per_condition())
    # 5 min idle (the filtered state converges at rest), then 3000 rpm
    run = plant_run([Segment(300.0, 0.0, 0.0, 22.0), Segment(1300.0, 3000.0, 5.0, 22.0)], seed=4)
    return cfg, samples_of(run)


def _rig(loaded_model, identified, edit: Callable[[Any], None] | None = None) -> Rig:  # type: ignore[no-untyped-def]
    cfg, samples = identified
    core = ServiceCore(cfg, model=loaded_model)
    now = [samples[0].t]

    def run(request: JobRequest) -> JobOutcome:  # changes a result before the core records it
        outcome = run_job(loaded_model, request)
        if outcome.result is not None and edit is not None:
            edit(outcome.result)
        return outcome

    svc = SoftSensorService(core, worker=None, clock=lambda: now[0], run_job=run)
    rig = Rig(core, svc, now, samples[-1])
    for s in samples:
        rig.feed(s)
    return rig


def _daq(last: Sample, quality: Quality | np.ndarray) -> DaqReading:
    q = np.full(32, np.uint8(quality)) if isinstance(quality, Quality) else quality
    amb_q = Quality.STALE if isinstance(quality, Quality) and quality is Quality.STALE else Quality.OK
    return DaqReading(
        t=last.t,
        temps_c=np.asarray(last.temps_c, float),
        ambient_c=float(last.ambient_c),
        status=np.zeros(32, np.int64),
        counter=1,
        quality=np.asarray(q, np.uint8),
        ambient_quality=amb_q,
    )


def _can(last: Sample, quality: Quality = Quality.OK) -> CanReading:
    status = SensorStatus.FAULT if quality is Quality.FAULT else SensorStatus.OK
    return CanReading(last.t, float(last.speed_rpm), float(last.torque_nm), status, 0, quality)


# What the drivers hand the acquisition in each failure, after their own staleness limit (drivers.md):
# unreachable, hung, closing connections, garbage replies and a frozen counter all end as the last values
# with every channel STALE (ModbusDaq.current()); a DAQ never heard from gives None (NO_DATA).
Failure = Callable[[Sample], tuple[DaqReading | None, CanReading | None]]
FAILURES: dict[str, tuple[Failure, str]] = {
    "daq stale (unreachable, hung, dropping, garbage, frozen)": (
        lambda s: (_daq(s, Quality.STALE), _can(s)),
        "daq_no_good_data",
    ),
    "daq never answered": (lambda s: (None, _can(s)), "daq_no_good_data"),
    "9 channels open circuit (23 < 24 usable)": (
        lambda s: (_daq(s, np.array([Quality.OPEN_CIRCUIT] * 9 + [Quality.OK] * 23, np.uint8)), _can(s)),
        "daq_no_good_data",
    ),
    "can silent": (lambda s: (_daq(s, Quality.OK), _can(s, Quality.STALE)), "can_no_good_data"),
    "can fault status": (lambda s: (_daq(s, Quality.OK), _can(s, Quality.FAULT)), "can_no_good_data"),
}


@pytest.mark.parametrize("name", list(FAILURES))
def test_stale_and_not_ready_within_the_limit_when_good_data_stop(loaded_model, identified, name) -> None:  # type: ignore[no-untyped-def]
    failure, code = FAILURES[name]
    rig = _rig(loaded_model, identified)
    snap = rig.svc.chtc()
    assert snap is not None and snap.status is ChtcStatus.FRESH, snap and snap.reason
    assert rig.svc.ready().ready
    limit = rig.core.config.stale_after_s
    t_good = rig.last.t
    daq, can = failure(rig.last)
    t = t_good
    while True:  # the acquisition keeps appending a sample every period
        t = t + timedelta(seconds=PERIOD_S)
        rig.feed(combine(daq, can, t=t, n_channels=32))
        age = (rig.now[0] - t_good).total_seconds()
        snap = rig.svc.chtc()
        ready = rig.svc.ready()
        assert snap is not None
        if age <= limit:
            assert snap.status is ChtcStatus.FRESH and ready.ready, (age, ready.reasons)
            continue
        assert snap.status is ChtcStatus.STALE, age
        assert not ready.ready and any(r.startswith(code) for r in ready.reasons), ready.reasons
        assert not snap.usable_for_compensation and snap.reason is not None
        assert snap.reason.startswith("stale: ") and code in snap.reason
        assert age <= limit + PERIOD_S + 1.0
        break


def test_fresh_again_when_good_data_return(loaded_model, identified) -> None:  # type: ignore[no-untyped-def]
    rig = _rig(loaded_model, identified)
    t = rig.last.t
    for _ in range(8):
        t += timedelta(seconds=PERIOD_S)
        rig.feed(combine(_daq(rig.last, Quality.STALE), _can(rig.last), t=t, n_channels=32))
    assert rig.svc.chtc().status is ChtcStatus.STALE  # type: ignore[union-attr]
    t += timedelta(seconds=PERIOD_S)
    rig.feed(replace(rig.last, t=t))
    assert rig.svc.ready().ready
    assert rig.svc.chtc().status is ChtcStatus.FRESH  # type: ignore[union-attr]


def test_no_sample_at_all_for_the_limit_is_stale(loaded_model, identified) -> None:  # type: ignore[no-untyped-def]
    rig = _rig(loaded_model, identified)
    rig.now[0] = rig.last.t + timedelta(seconds=rig.core.config.stale_after_s + 1)
    reasons = rig.svc.ready().reasons
    assert any(r.startswith("no_sample") for r in reasons), reasons
    assert rig.svc.chtc().status is ChtcStatus.STALE  # type: ignore[union-attr]


def _all_identified(result: Any) -> None:
    """Every H identified, with a band to match (σ(ln H) 0.1: /chtc judges the flag on its served band)."""
    result.identified[:] = True
    result.h_ci95[:, 0] = result.h * np.exp(-0.2)
    result.h_ci95[:, 1] = result.h * np.exp(0.2)


def test_usable_for_compensation_when_fresh_identified_and_inside_the_box(loaded_model, identified) -> None:  # type: ignore[no-untyped-def]
    rig = _rig(loaded_model, identified, edit=_all_identified)
    snap = rig.svc.chtc()
    assert snap is not None and snap.status is ChtcStatus.FRESH
    assert snap.usable_for_compensation and snap.reason is None


def test_h_on_a_bound_is_not_identified_and_not_usable(loaded_model, identified) -> None:  # type: ignore[no-untyped-def]
    """An identification ending with H3 on the box's upper bound (200 W/(m²·K)), all others identified: the
    service flags it (from the search box, also for results that do not carry the flag) and says why."""

    def on_bound(result: Any) -> None:
        _all_identified(result)
        result.h[2] = loaded_model.rom.h_box[1]

    rig = _rig(loaded_model, identified, edit=on_bound)
    snap = rig.svc.chtc()
    # never `fresh` with an H on a bound, though the data and the condition are current
    assert snap is not None and snap.status is ChtcStatus.AT_BOUND
    assert snap.at_bound is not None and snap.at_bound.tolist() == [False, False, True] + [False] * 4
    assert not snap.identified[2] and snap.identified[[0, 1, 3, 4, 5, 6]].all()
    assert not snap.usable_for_compensation
    assert snap.reason is not None and snap.reason.startswith("at_bound: H3")


def test_not_identified_and_condition_change_are_not_usable(loaded_model, identified) -> None:  # type: ignore[no-untyped-def]
    def weak_h1(result: Any) -> None:
        _all_identified(result)
        result.identified[0] = False

    rig = _rig(loaded_model, identified, edit=weak_h1)
    snap = rig.svc.chtc()
    assert snap is not None and not snap.usable_for_compensation
    assert snap.reason is not None and snap.reason.startswith("not_identified: H1")
    t = rig.last.t
    for _ in range(3):  # the speed leaves the condition: the detector sees it change
        t += timedelta(seconds=PERIOD_S)
        rig.feed(replace(rig.last, t=t, speed_rpm=4500.0))
    snap = rig.svc.chtc()
    assert snap is not None and snap.status is ChtcStatus.IDENTIFYING
    assert not snap.usable_for_compensation and snap.reason.startswith("condition_changed")  # type: ignore[union-attr]


def test_a_stored_negative_lower_bound_is_not_served() -> None:
    """Rows stored with the former linear CI may hold a negative lower bound; H > 0, so 0 is served (the
    same mapping serves a row read back and a record just finished)."""
    from service.serve.views import data_to_record

    t = datetime(2026, 1, 1, tzinfo=UTC)
    cond = ConditionSnapshot(
        id=1, speed_rpm=3000.0, torque_nm=5.0, ambient_c=22.0, since=t, state=ConditionState.STABLE
    )
    data = IdentificationData(
        id=1, condition_id=1, started_at=t, finished_at=t, window_start=t, window_end=t, reason="r",
        outcome="ok", method="hybrid", model_version="m", h=[50.0] * 7,
        ci95_lo=[-16.7, 40.0, None, 1, 2, 3, 4], ci95_hi=[116.7] * 7, identified=[False] + [True] * 6,
    )  # fmt: skip
    rec = data_to_record(data, cond)
    assert rec.ci95_lo[0] == 0.0 and rec.ci95_lo[1] == 40.0 and np.isnan(rec.ci95_lo[2])
