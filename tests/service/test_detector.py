"""The condition-change detector driven with events only: noise, spikes, drift, steps, several changes."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from service.identify.detector import (
    ConditionChanged,
    ConditionDetector,
    DetectorError,
    DetectorStatus,
    OperatingPoint,
    SampleEvent,
)
from tests.engine_config import product_core

CFG = product_core().detector  # the product's: 150 rpm, 1 N·m, 1 °C, held 60 s, median of 3, gap 120 s
DT = 10.0


def feed(det: ConditionDetector, speed, torque, ambient, *, t0: float = 0.0) -> list[ConditionChanged]:
    out: list[ConditionChanged] = []
    for k, (s, m, a) in enumerate(zip(speed, torque, ambient, strict=True)):
        out += det.handle(
            SampleEvent(t=t0 + k * DT, speed_rpm=float(s), torque_nm=float(m), ambient_c=float(a))
        )
    return out


def const(n: int, value: float) -> np.ndarray:
    return np.full(n, value)


def test_first_condition_after_hold_with_means():
    det = ConditionDetector(CFG)
    rng = np.random.default_rng(1)
    n = 20
    speed = 3000 + rng.normal(0, 5, n)
    torque = 2.0 + rng.normal(0, 0.05, n)
    amb = 23.2 + rng.normal(0, 0.05, n)
    changes = feed(det, speed, torque, amb)
    assert len(changes) == 1
    c = changes[0]
    assert c.previous is None and c.t_start == 0.0 and c.t_confirmed == CFG.hold_s
    k = int(CFG.hold_s / DT) + 1  # samples 0..6 inclusive form the hold period
    assert c.point.speed_rpm == pytest.approx(speed[:k].mean())
    assert c.point.ambient_c == pytest.approx(amb[:k].mean())
    assert det.status is DetectorStatus.STABLE


def test_noise_never_triggers():
    det = ConditionDetector(CFG, reference=OperatingPoint(speed_rpm=3000, torque_nm=2.0, ambient_c=23.0))
    rng = np.random.default_rng(2)
    n = 2000
    changes = feed(det, 3000 + rng.normal(0, 30, n), 2 + rng.normal(0, 0.2, n), 23 + rng.normal(0, 0.2, n))
    assert changes == []
    assert det.status is DetectorStatus.STABLE


def test_short_spikes_do_not_trigger():
    det = ConditionDetector(CFG, reference=OperatingPoint(speed_rpm=3000, torque_nm=2.0, ambient_c=23.0))
    speed = const(200, 3000.0)
    speed[50] = 9000  # an isolated outlier (median-filtered away)
    speed[100:105] = 4500  # a 40 s excursion, shorter than the 60 s hold
    torque = const(200, 2.0)
    torque[150:153] = 8.0
    changes = feed(det, speed, torque, const(200, 23.0))
    assert changes == []


def test_step_reports_mean_and_change_instant():
    det = ConditionDetector(CFG, reference=OperatingPoint(speed_rpm=3000, torque_nm=2.0, ambient_c=23.0))
    speed = np.r_[const(30, 3000.0), const(30, 4000.0)]
    changes = feed(det, speed, const(60, 2.0), const(60, 23.0))
    assert len(changes) == 1
    c = changes[0]
    # with the 3-sample median the step is seen on its second sample (index 31 -> t = 310 s)
    assert c.t_start == pytest.approx(310.0)
    assert c.t_confirmed == pytest.approx(310.0 + CFG.hold_s)
    assert c.point.speed_rpm == pytest.approx(4000.0)
    assert c.previous == OperatingPoint(speed_rpm=3000, torque_nm=2.0, ambient_c=23.0)
    assert "speed" in c.reason and "torque" not in c.reason


def test_slow_drift_within_threshold_is_ignored_and_beyond_triggers_once():
    det = ConditionDetector(CFG, reference=OperatingPoint(speed_rpm=3000, torque_nm=2.0, ambient_c=23.0))
    n = 1000  # 10 000 s, ambient +3 °C: crosses the 1 °C threshold, then again from the new reference
    amb = np.linspace(23.0, 26.0, n)
    changes = feed(det, const(n, 3000.0), const(n, 2.0), amb)
    assert 1 <= len(changes) <= 3
    for c in changes:
        idx = np.arange(n)[(np.arange(n) * DT >= c.t_start) & (np.arange(n) * DT <= c.t_confirmed)]
        assert c.point.ambient_c == pytest.approx(amb[idx].mean())
        assert abs(c.point.ambient_c - c.previous.ambient_c) > CFG.ambient_threshold_c - 0.1
    gaps = np.diff([c.t_start for c in changes])
    assert np.all(gaps > CFG.hold_s)

    det2 = ConditionDetector(CFG, reference=OperatingPoint(speed_rpm=3000, torque_nm=2.0, ambient_c=23.0))
    assert feed(det2, const(n, 3000.0), const(n, 2.0), np.linspace(23.0, 23.9, n)) == []


def test_multiple_changes_and_step_during_hold():
    det = ConditionDetector(CFG)
    speed = np.r_[const(20, 3000.0), const(3, 4000.0), const(30, 5000.0), const(30, 3000.0)]
    n = len(speed)
    changes = feed(det, speed, const(n, 2.0), const(n, 22.0))
    assert [round(c.point.speed_rpm) for c in changes] == [3000, 5000, 3000]
    assert [c.index for c in changes] == [1, 2, 3]
    assert changes[1].previous.speed_rpm == pytest.approx(3000)


def test_nan_samples_are_ignored_and_counted():
    det = ConditionDetector(CFG, reference=OperatingPoint(speed_rpm=3000, torque_nm=2.0, ambient_c=23.0))
    speed = const(20, 3000.0)
    speed[5:8] = np.nan
    assert feed(det, speed, const(20, 2.0), const(20, 23.0)) == []
    assert det.ignored_samples == 3


def test_gap_restarts_hold():
    det = ConditionDetector(CFG, reference=OperatingPoint(speed_rpm=3000, torque_nm=2.0, ambient_c=23.0))
    assert det.handle(SampleEvent(t=0.0, speed_rpm=4000, torque_nm=2, ambient_c=23)) == []
    assert det.handle(SampleEvent(t=10.0, speed_rpm=4000, torque_nm=2, ambient_c=23)) == []
    assert (
        det.handle(SampleEvent(t=500.0, speed_rpm=4000, torque_nm=2, ambient_c=23)) == []
    )  # gap > max_gap_s: hold restarts at 500 s
    assert det.status is DetectorStatus.PENDING
    assert det.handle(SampleEvent(t=550.0, speed_rpm=4000, torque_nm=2, ambient_c=23)) == []
    out = det.handle(SampleEvent(t=560.0, speed_rpm=4000, torque_nm=2, ambient_c=23))
    assert len(out) == 1 and out[0].t_start == 500.0


def test_bad_config_and_time_order():
    with pytest.raises(DetectorError, match="hold_s"):
        replace(CFG, hold_s=-1)
    with pytest.raises(DetectorError, match="median_samples"):
        replace(CFG, median_samples=0)
    det = ConditionDetector(CFG)
    det.handle(SampleEvent(t=10.0, speed_rpm=3000, torque_nm=2, ambient_c=23))
    with pytest.raises(DetectorError, match="older"):
        det.handle(SampleEvent(t=5.0, speed_rpm=3000, torque_nm=2, ambient_c=23))
