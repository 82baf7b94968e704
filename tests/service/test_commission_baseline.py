"""The commissioning's offset baseline (issue 40 part 3, ``service.contracts.commissionbaseline``): the
thermal test's initial rest gives the offsets (close to the plant's), kept in the stored commissioning's
report; a core without a stored baseline starts with it (source ``commissioning``, 1σ widened by
``AGE_SD_C``), adopts it when mechanics are set at run time, and never puts it over a rest baseline, which
replaces it."""

from __future__ import annotations

import json
from dataclasses import replace
from datetime import UTC, datetime, timedelta
from pathlib import Path

import numpy as np
import pytest

from model.plant import Segment, VirtualPlant
from model.plantmech import mechanics_for_seed
from service.acquire.calibration import BaselineTaken, CalibrationStatus, OffsetCalibrator, Reading
from service.contracts.calibration import Calibration
from service.contracts.commissionbaseline import (
    AGE_SD_C,
    BASELINE_KEY,
    baseline_entry,
    commissioning_baseline,
)
from service.contracts.errors import RecordError
from service.contracts.mechanics import MechanicsCalibration
from service.core.baselinecheck import CHECK_S, MAX_SLOPE, BaselineCheck, needs_check
from service.core.config import Restored
from service.core.events import BaselineAdopted, Calibrated, Log, Store
from service.core.machine import ServiceCore
from service.modelload import LoadedModel
from service.shell.commissioning import field_history
from simulator.thermaltest import write_thermal_test
from tests.engine_config import product_core

from .conftest import plant_run, samples_of
from .drive import feed as feed_core

T = datetime(2026, 3, 1, 6, 0, tzinfo=UTC)
OFFSETS = np.random.default_rng(11).uniform(-0.2, 0.2, 32)
CAL = product_core().calibration  # the product's equilibrium test (identification.offset_*)


def readings(n: int) -> list[Reading]:
    """n samples every 10 s at rest at 20 °C ambient, the sensors with ``OFFSETS`` and σ 0.15 °C noise."""
    rng = np.random.default_rng(0)
    return [
        Reading(
            t=T + timedelta(seconds=10 * k),
            temps_c=20.0 + OFFSETS + 0.15 * rng.standard_normal(32),
            ok=np.ones(32, bool),
            ambient_c=20.0,
            speed_rpm=0.0,
        )
        for k in range(n)
    ]


def rest_baseline(seed: int = 1, source: str = "auto") -> Calibration:
    rng = np.random.default_rng(seed)
    offsets = rng.uniform(-0.2, 0.2, 32)
    offsets[4] = np.nan  # an open channel during the rest
    return Calibration(
        offsets_c=offsets,
        sd_c=rng.uniform(0.005, 0.02, 32),
        t_from=T,
        t_to=T + timedelta(minutes=15),
        samples=91,
        source=source,
    )


def mechanics(baseline: Calibration | None, **report: object) -> MechanicsCalibration:
    return MechanicsCalibration(
        x=(0.6, 1.0, 1.0),
        cov=((0.01, 0.0, 0.0), (0.0, 0.001, 0.0), (0.0, 0.0, 0.001)),
        at=T + timedelta(hours=5),
        set_by="test",
        source="cli",
        explained=True,
        report={BASELINE_KEY: baseline_entry(baseline), **report},
    )


# ------------------------------------------------------------------------ the contract (pure)


def test_the_baseline_round_trips_through_the_stored_report_json_widened_by_its_age() -> None:
    b = rest_baseline()
    stored = json.loads(json.dumps(mechanics(b).values()["report"]))  # the JSON column's content
    got = commissioning_baseline(replace(mechanics(None), report=stored))
    assert got is not None and got.source == "commissioning"
    assert (got.t_from, got.t_to, got.samples) == (b.t_from, b.t_to, b.samples)
    np.testing.assert_array_equal(np.isnan(got.offsets_c), np.isnan(b.offsets_c))
    np.testing.assert_allclose(got.applied(), b.applied(), atol=1e-5)
    np.testing.assert_allclose(got.sd_c, np.hypot(b.sd_c, AGE_SD_C), atol=1e-5)
    assert np.all(got.sd_c > AGE_SD_C)


def test_no_commissioning_or_no_baseline_in_its_report_gives_none_and_a_bad_entry_is_named() -> None:
    assert commissioning_baseline(None) is None
    assert commissioning_baseline(mechanics(None)) is None
    assert commissioning_baseline(replace(mechanics(None), report={})) is None  # a report made before
    entry = baseline_entry(rest_baseline())
    assert entry is not None
    for broken, field in (
        ({**entry, "sd_c": entry["sd_c"][:31]}, "sd_c"),
        ({**entry, "offsets_c": "x"}, "offsets_c"),
        ({**entry, "t_to": "yesterday"}, "t_from/t_to/samples"),
        ({k: v for k, v in entry.items() if k != "samples"}, "t_from/t_to/samples"),
    ):
        with pytest.raises(RecordError, match=f"{BASELINE_KEY}.{field}"):
            commissioning_baseline(replace(mechanics(None), report={BASELINE_KEY: broken}))


def test_the_calibrator_adopts_a_baseline_only_without_one_and_the_next_rest_replaces_it() -> None:
    assert CAL is not None
    commissioned = commissioning_baseline(mechanics(rest_baseline(seed=3)))
    assert commissioned is not None
    cal = OffsetCalibrator(config=CAL, sample_period_s=10.0)
    out = cal.adopt(commissioned)
    assert [type(i) for i in out] == [BaselineTaken] and cal.current is commissioned
    assert cal.status is CalibrationStatus.CALIBRATED
    assert (
        cal.adopt(rest_baseline(seed=4)) == [] and cal.current is commissioned
    )  # never replaced but at rest
    taken = [i for r in readings(40) for i in cal.handle(r) if isinstance(i, BaselineTaken)]
    assert len(taken) == 1 and cal.current is not None and cal.current.source == "auto"
    rested = cal.current
    assert cal.adopt(commissioned) == [] and cal.current is rested


# ------------------------------------------------------------------------ the thermal test's rest


def test_field_history_keeps_the_baseline_of_the_tests_rest_close_to_the_plants_offsets(
    tmp_path: Path, loaded_model: LoadedModel
) -> None:
    """The recommended profile's 15-min rest and the start of its first heat-up (a plant with offsets)."""
    mech = mechanics_for_seed(3)
    plant = VirtualPlant(loaded_model.spec, mesh_size_m=0.004, seed=3, mechanics=mech, offsets_c=OFFSETS)
    profile = (Segment(900.0, 0.0, 0.0, 21.0), Segment(60.0, 4000.0, 5.0, 21.0))
    t = write_thermal_test(tmp_path, mechanics=mech, profile=profile, seed=3, plant=plant)
    hist = field_history(loaded_model, product_core(), t.temperatures, t.canlog)
    b = hist.baseline
    assert b is not None and b.source == "auto" and hist.baseline_note == ""
    # the whole rest (the baseline refined while it lasted), not the first 5 min it was taken on
    assert b.samples >= 85 and (b.t_to - b.t_from).total_seconds() >= 840.0
    err = b.offsets_c - OFFSETS
    assert np.all(np.abs(err) < 4.0 * b.sd_c), np.abs(err / b.sd_c).max()
    assert float(np.sqrt(np.mean(err**2))) < 0.03  # the ±0.2 °C offsets known to a few hundredths

    running = field_history(
        loaded_model, product_core(), *_test_files(tmp_path / "running", mech, plant)
    )  # a test that starts turning: no rest, no baseline, said why
    assert running.baseline is None and "initial rest" in running.baseline_note


def _test_files(out: Path, mech: object, plant: VirtualPlant) -> tuple[Path, Path]:
    t = write_thermal_test(
        out,
        mechanics=mech,  # type: ignore[arg-type]
        profile=(Segment(120.0, 4000.0, 5.0, 21.0),),
        seed=3,
        plant=plant,
    )
    return t.temperatures, t.canlog


# ------------------------------------------------------------------------ the core


def test_a_core_without_a_baseline_adopts_the_commissionings_and_stores_it(loaded_model: LoadedModel) -> None:
    core = ServiceCore(product_core(), model=loaded_model)
    assert core.view().calibration is None
    commissioned = commissioning_baseline(mechanics(rest_baseline()))
    assert commissioned is not None
    out = core.handle(BaselineAdopted("baseline-1", commissioned))
    assert [i.calibration for i in out if isinstance(i, Calibrated)] == [commissioned]
    assert [i.record for i in out if isinstance(i, Store)] == [commissioned]  # restored at the next start
    assert any("from the commissioning's rest" in i.message for i in out if isinstance(i, Log))
    view = core.view()
    assert view.calibration is commissioned and view.offset_sd_c is not None
    np.testing.assert_allclose(view.offset_sd_c, commissioned.sd_c)
    # the H bands no longer carry the no-baseline widening
    assert view.h_form_sd == pytest.approx(product_core().h_form_sd)


def test_a_core_with_a_rest_baseline_refuses_the_commissionings(loaded_model: LoadedModel) -> None:
    rested = rest_baseline(seed=7)
    core = ServiceCore(product_core(), model=loaded_model, restored=Restored(calibration=rested))
    commissioned = commissioning_baseline(mechanics(rest_baseline(seed=8)))
    assert commissioned is not None
    assert core.handle(BaselineAdopted("baseline-1", commissioned)) == []
    assert core.view().calibration is rested


def test_a_restart_with_the_stored_commissioning_and_no_baseline_starts_calibrated(
    tmp_path: Path, loaded_model: LoadedModel
) -> None:
    """Real SQLite: the commissioning stored (its report holds the baseline), no offset baseline; the restored
    core starts with the commissioning's offsets (source commissioning) and a rest replaces them."""
    from service.host.persistence import open_persistence
    from service.settings import Settings
    from service.store.mechanics import mechanics_record

    db = Settings().database.model_copy(update={"url": f"sqlite:///{tmp_path / 'chtc.db'}"})
    b = rest_baseline(seed=5)
    first = open_persistence(db, migrate=True)
    assert first.sink.submit(mechanics_record(mechanics(b)))
    first.close()

    second = open_persistence(db, migrate=False)
    try:
        restored = second.restored
        assert restored.calibration is None and restored.mechanics is not None
        core = ServiceCore(product_core(), model=loaded_model, restored=restored)
    finally:
        second.close()
    view = core.view()
    assert view.calibration is not None and view.calibration.source == "commissioning"
    np.testing.assert_allclose(view.calibration.applied(), b.applied(), atol=1e-5)
    assert view.offset_sd_c is not None and np.all(view.offset_sd_c >= AGE_SD_C)
    run = plant_run([Segment(600.0, 0.0, 0.0, 21.0)], offsets_c=OFFSETS)
    out = feed_core(core, samples_of(run, t0=(T + timedelta(days=1)).timestamp()))
    logs = [i.message for i in out if isinstance(i, Log)]
    assert any("from the commissioning's rest" in m for m in logs), logs[:3]
    after = core.view().calibration
    assert after is not None and after.source == "auto"  # the rest's own baseline replaced it
    assert np.all(np.abs(after.offsets_c - OFFSETS) < 0.1)


# ------------------------------------------------------------------------ do the offsets still fit?


def test_the_check_tells_offsets_that_fit_from_offsets_that_are_not_there() -> None:
    """β = Σ r·o / Σ o² over ``check_s``: residuals that do not follow the offsets keep them (β ≈ 0),
    residuals r = −o (the sensors have none) give β ≈ −1; nothing before ``check_s``."""
    rng = np.random.default_rng(2)
    usable = np.ones(32, bool)
    usable[3] = False
    for sensor_offsets, lo, hi in ((OFFSETS, -0.2, 0.2), (np.zeros(32), -1.2, -0.8)):
        check = BaselineCheck(OFFSETS, check_s=600.0)
        betas = []
        for k in range(61):
            truth = 30.0 + rng.normal(0.0, 1.0, 32)
            measured = truth + sensor_offsets + rng.normal(0.0, 0.1, 32)
            predicted = truth + rng.normal(0.0, 0.05, 32)  # the filter's estimate: close to the truth
            betas.append(check.add(10.0 * k, measured, usable, predicted))
        assert betas[:-1] == [None] * 60 and betas[-1] is not None
        assert lo < betas[-1] < hi, betas[-1]
    assert (MAX_SLOPE, CHECK_S) == (-0.5, 600.0)
    assert needs_check(OFFSETS) and not needs_check(0.02 * OFFSETS / np.abs(OFFSETS).max())


@pytest.mark.parametrize("sensors_have_them", [True, False])
def test_the_core_keeps_the_commissionings_offsets_only_if_the_sensors_still_have_them(
    sensors_have_them: bool, loaded_model: LoadedModel
) -> None:
    """A start while machining with the commissioning's offsets adopted: after 10 min of live state they are
    kept when the plant's sensors have them, dropped (no baseline, said why) when they have none."""
    run = plant_run([Segment(780.0, 5000.0, 5.0, 21.0)], offsets_c=OFFSETS if sensors_have_them else None)
    core = ServiceCore(product_core(), model=loaded_model)
    commissioned = Calibration(
        offsets_c=OFFSETS,
        sd_c=np.full(32, np.hypot(0.01, AGE_SD_C)),
        t_from=T - timedelta(days=30),
        t_to=T - timedelta(days=30) + timedelta(minutes=15),
        samples=91,
        source="commissioning",
    )
    core.handle(BaselineAdopted("baseline-1", commissioned))
    assert core.view().offsets_unchecked  # not a founded baseline for the verdict until checked
    logs = [i.message for i in feed_core(core, samples_of(run)) if isinstance(i, Log)]
    said = [m for m in logs if "commissioning's sensor offsets" in m]
    assert len(said) == 1, logs
    view = core.view()
    assert not view.offsets_unchecked
    if sensors_have_them:
        assert "fit the sensors" in said[0] and view.calibration is commissioned
    else:
        assert "do NOT fit" in said[0] and view.calibration is None
        assert view.offset_sd_c is not None and np.all(view.offset_sd_c > 0.1)  # back to unknown offsets
