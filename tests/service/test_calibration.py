"""Sensor offset calibration: the equilibrium detector, the baseline state machine, its wiring in the core."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta

import numpy as np
import pytest

from model.plant import Segment
from service.acquire.calibration import (
    BaselineRefined,
    BaselineRejected,
    BaselineRequest,
    BaselineTaken,
    CalibrationStatus,
    OffsetCalibrator,
    Reading,
    equilibrium,
)
from service.core.config import CoreConfig
from service.core.events import Launch, SampleReceived, Store
from service.core.machine import ServiceCore
from service.modelload import LoadedModel
from tests.engine_config import product_core

from .conftest import plant_run, samples_of
from .drive import feed as feed_core

T = datetime(2026, 3, 1, 6, 0, tzinfo=UTC)
OFFSETS = np.random.default_rng(5).uniform(-0.2, 0.2, 32)
CAL = product_core().calibration  # the product's equilibrium test (identification.offset_*)
assert CAL is not None


def calibrator() -> OffsetCalibrator:
    """The product's calibrator at the product's 10-s sample period."""
    assert CAL is not None
    return OffsetCalibrator(config=CAL, sample_period_s=10.0)


def readings(
    n: int, *, start: int = 0, speed: float = 0.0, excess: float = 0.0, decay_s: float = 0.0, seed: int = 0
):  # type: ignore[no-untyped-def]
    """n samples every 10 s at 20 °C ambient: offsets + noise (σ 0.15 °C) + a spindle excess decaying
    with ``decay_s`` (0: constant)."""
    rng = np.random.default_rng(seed)
    out = []
    for k in range(start, start + n):
        warm = excess * (np.exp(-10.0 * k / decay_s) if decay_s else 1.0)
        temps = 20.0 + warm + OFFSETS + 0.15 * rng.standard_normal(32)
        out.append(
            Reading(
                t=T + timedelta(seconds=10 * k),
                temps_c=temps,
                ok=np.ones(32, bool),
                ambient_c=20.0,
                speed_rpm=speed,
            )
        )
    return out


def feed(cal: OffsetCalibrator, items) -> list:  # type: ignore[no-untyped-def]
    out = []
    for r in items:
        out += cal.handle(r)
    return out


def test_a_rest_at_the_ambient_gives_a_baseline_with_the_offsets() -> None:
    cal = calibrator()
    assert cal.status is CalibrationStatus.NO_BASELINE
    # unknown offsets: ±0.3 °C uniform, 1σ 0.3/√3 = 0.1732 (identification.offset_sd_c, rounded to 0.173)
    assert np.allclose(cal.offset_sd(), 0.173)
    taken = feed(cal, readings(31))
    assert len(taken) == 1 and isinstance(taken[0], BaselineTaken)
    c = taken[0].calibration
    # 30 samples span 290 s: the detector allows 5 % for the sample times' jitter around the 10-s grid
    assert cal.status is CalibrationStatus.CALIBRATED and c.source == "auto" and c.samples == 30
    assert c.t_to == T + timedelta(seconds=290)
    sd = 0.15 / np.sqrt(30)
    assert np.all(np.abs(c.offsets_c - OFFSETS) < 4.5 * sd)
    expected = np.sqrt(sd**2 + 0.005**2)  # the channel's scatter / √n, plus the equilibrium's own 1σ
    assert np.median(c.sd_c) == pytest.approx(expected, rel=0.15)
    assert np.all((c.sd_c > 0.5 * expected) & (c.sd_c < 1.5 * expected))
    assert cal.current is not None and cal.current.samples == 31  # the 31st sample refined it
    np.testing.assert_allclose(cal.offsets(), cal.current.offsets_c)


def test_a_longer_rest_refines_the_same_baseline_silently() -> None:
    """No new ``BaselineTaken`` (no operator message); a ``BaselineRefined`` to store each time the samples
    doubled (30 -> 60 -> 120) and when the rest ends, carrying the in-memory baseline."""
    cal = calibrator()
    first = feed(cal, readings(31))
    later = feed(cal, readings(150, start=31, seed=1))
    assert len(first) == 1 and isinstance(first[0], BaselineTaken) and first[0].calibration.samples == 30
    assert [type(i) for i in later] == [BaselineRefined, BaselineRefined]
    assert [i.calibration.samples for i in later] == [60, 120]
    assert cal.current is not None and cal.current.samples == 181
    ended = feed(cal, readings(2, start=181, speed=3000.0))
    assert len(ended) == 1 and ended[0].calibration is cal.current
    assert np.all(np.abs(cal.current.offsets_c - OFFSETS) < 4.5 * 0.15 / np.sqrt(181))
    assert cal.current.t_from == T
    assert np.median(cal.current.sd_c) < 0.5 * np.median(first[0].calibration.sd_c)


def test_a_cooling_or_warm_spindle_is_not_an_equilibrium() -> None:
    cooling = calibrator()
    assert feed(cooling, readings(60, excess=3.0, decay_s=1800.0)) == []
    assert cooling.current is None and cooling.status is CalibrationStatus.SETTLING
    warm = readings(31, excess=0.5)  # flat but 0.5 °C above the ambient
    assert equilibrium(warm, CAL) == "the spindle is not at the ambient temperature"
    assert "drifting" in str(equilibrium(readings(31, excess=3.0, decay_s=1800.0), CAL))


def test_running_resets_the_rest_and_rearms_the_automatic_baseline() -> None:
    cal = calibrator()
    feed(cal, readings(31))
    feed(cal, readings(5, start=31, speed=3000.0))
    assert cal.status is CalibrationStatus.CALIBRATED  # the offsets are kept while the spindle runs
    rejected = cal.handle(BaselineRequest(T + timedelta(seconds=400)))
    assert isinstance(rejected[0], BaselineRejected) and "no samples at rest" in rejected[0].reason
    again = feed(cal, readings(31, start=40, seed=2))
    assert len(again) == 1 and isinstance(again[0], BaselineTaken)


def test_a_manual_request_takes_a_baseline_or_names_why_not() -> None:
    cal = calibrator()
    feed(cal, readings(10))
    short = cal.handle(BaselineRequest(T))
    assert isinstance(short[0], BaselineRejected) and "at rest for 90 s only" in short[0].reason
    feed(cal, readings(25, start=10, seed=3))
    manual = cal.handle(BaselineRequest(T))
    assert isinstance(manual[0], BaselineTaken) and manual[0].calibration.source == "manual"


def test_an_open_channel_keeps_no_offset_and_the_prior_uncertainty() -> None:
    cal = calibrator()
    items = readings(31)
    items = [
        Reading(t=r.t, temps_c=r.temps_c, ok=np.arange(32) != 4, ambient_c=r.ambient_c, speed_rpm=r.speed_rpm)
        for r in items
    ]
    c = feed(cal, items)[0].calibration
    assert np.isnan(c.offsets_c[4]) and cal.offsets()[4] == 0.0
    assert c.sd_c[4] == pytest.approx(
        np.hypot(0.173, 0.005)
    )  # the prior's 1σ (offset_sd_c) and equilibrium's


def test_the_core_zeroes_the_offsets_of_its_jobs(loaded_model: LoadedModel) -> None:
    """A log that starts at rest: the core takes the baseline and every identification job carries the
    offsets (close to the plant's) and their 1σ; with calibration off the job carries none."""
    profile = [Segment(900.0, 0.0, 0.0, 21.0), Segment(900.0, 3000.0, 5.0, 21.0)]
    run = plant_run(profile, offsets_c=OFFSETS)

    def first_request(config: CoreConfig, run=run):  # type: ignore[no-untyped-def]
        core = ServiceCore(config, model=loaded_model)
        for n, s in enumerate(samples_of(run), start=1):
            started = [i for i in core.handle(SampleReceived(f"sample-{n}", s)) if isinstance(i, Launch)]
            if started:
                return core, started[0].request
        raise AssertionError("no identification was launched")

    core, req = first_request(product_core())
    assert core.view().calibration is not None
    assert np.all(np.abs(req.offsets_c - OFFSETS) < 4.5 * 0.15 / np.sqrt(85))
    assert np.all(req.offset_sd_c < 0.03)
    # without calibration the filtered state needs offset-free sensors to converge (docs/design/estimator.md)
    _, plain = first_request(product_core(identification={"offset_calibration": False}), plant_run(profile))
    assert plain.offsets_c is None and plain.offset_sd_c is None


def test_a_baseline_taken_by_the_core_is_stored_and_a_restarted_core_starts_with_it(
    tmp_path, loaded_model: LoadedModel
) -> None:
    """Real SQLite through the service's writer: the core's baseline becomes an ``offset_calibrations`` row;
    after a restart the restored core is calibrated with the same offsets and 1σ before any rest."""
    from service.host.persistence import open_persistence
    from service.settings import Settings

    db = Settings().database.model_copy(update={"url": f"sqlite:///{tmp_path / 'chtc.db'}"})
    run = plant_run([Segment(600.0, 0.0, 0.0, 21.0), Segment(300.0, 3000.0, 5.0, 21.0)], offsets_c=OFFSETS)
    first = open_persistence(db, migrate=True)
    core = ServiceCore(product_core(), model=loaded_model)
    for ins in feed_core(core, samples_of(run)):
        if isinstance(ins, Store):
            first.sink.submit(ins.record)
    taken = core.view().calibration
    assert taken is not None and taken.source == "auto"
    first.close()

    second = open_persistence(db, migrate=False)
    try:
        restored = second.restored.calibration
        assert restored is not None and restored.t_to == taken.t_to
        fresh = ServiceCore(product_core(), model=loaded_model, restored=second.restored).view()
        assert fresh.calibration is not None and fresh.offset_sd_c is not None
        np.testing.assert_allclose(fresh.calibration.applied(), taken.applied())
        np.testing.assert_allclose(fresh.offset_sd_c, taken.sd_c)
    finally:
        second.close()
