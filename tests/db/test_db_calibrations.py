"""Sensor offset baselines survive a restart: written through the buffered writer, restored by
``open_persistence`` into ``Restored.calibration``; a bad stored row is named and kept, the rest restored.
Real SQLite and real PostgreSQL (``db_url``)."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta

import numpy as np
import pytest
from sqlalchemy import select

from service.contracts.calibration import Calibration
from service.contracts.records import ConditionStart
from service.host.persistence import open_persistence
from service.settings import Settings
from service.store import repository as repo
from service.store.calibrations import StoredCalibrationError, calibration_from_row
from service.store.errors import RecordError
from service.store.models import OffsetCalibrationRow

T0 = datetime(2026, 3, 1, 6, 0, 0, 250000, tzinfo=UTC)


def baseline(t_to: datetime, *, source: str = "auto", seed: int = 1) -> Calibration:
    rng = np.random.default_rng(seed)
    offsets = rng.uniform(-0.3, 0.3, 32)
    offsets[6] = np.nan  # an open channel during the rest: no offset
    sd = rng.uniform(0.005, 0.03, 32)
    return Calibration(
        offsets_c=offsets, sd_c=sd, t_from=t_to - timedelta(minutes=20), t_to=t_to, samples=121, source=source
    )


def db_settings(url: str):  # type: ignore[no-untyped-def]
    return Settings().database.model_copy(update={"url": url})


def assert_same(got: Calibration | None, want: Calibration) -> None:
    assert got is not None
    np.testing.assert_array_equal(np.isnan(got.offsets_c), np.isnan(want.offsets_c))
    np.testing.assert_allclose(
        got.offsets_c[~np.isnan(want.offsets_c)], want.offsets_c[~np.isnan(want.offsets_c)]
    )
    np.testing.assert_allclose(got.sd_c, want.sd_c)
    assert (got.t_from, got.t_to, got.samples, got.source) == (
        want.t_from,
        want.t_to,
        want.samples,
        want.source,
    )
    assert got.t_to.tzinfo is not None and got.t_to.utcoffset() == timedelta(0)


def test_the_newest_baseline_is_restored_after_a_restart(db_url: str) -> None:
    first = open_persistence(db_settings(db_url), migrate=True)
    assert first.restored.calibration is None
    older, newer = baseline(T0, seed=1), baseline(T0 + timedelta(hours=3), source="manual", seed=2)
    for c in (newer, older):  # stored out of order: the newest t_to wins, not the last written
        assert first.sink.submit(c)
    assert first.close().written == 2

    second = open_persistence(db_settings(db_url), migrate=False)
    try:
        assert second.restored_from_db
        assert_same(second.restored.calibration, newer)
        with repo.session_scope(second.session_factory) as s:
            page = repo.list_offset_calibrations(s, limit=10)
            assert page.total == 2 and [r.source for r in page.items] == ["manual", "auto"]
    finally:
        second.close()


def test_a_bad_stored_baseline_is_named_kept_and_the_rest_restored(db_url: str) -> None:
    first = open_persistence(db_settings(db_url), migrate=True)
    first.sink.submit(ConditionStart(id=7, started_at=T0, speed_rpm=3000.0, torque_nm=5.0, ambient_c=22.0))
    first.sink.submit(baseline(T0))
    first.close()
    with repo.session_scope(first.session_factory) as s:  # a later row, damaged: 31 channels
        bad = OffsetCalibrationRow(
            spindle_id="spindle1",
            t_from=T0,
            t_to=T0 + timedelta(hours=1),
            source="auto",
            samples=30,
            offsets_c=[0.1] * 31,
            sd_c=[0.01] * 31,
        )
        s.add(bad)
        s.flush()
        bad_id = bad.id

    said: list[str] = []
    second = open_persistence(db_settings(db_url), migrate=False, on_event=said.append)
    try:
        assert second.restored.calibration is None  # not a guess: no baseline, the CIs carry the tolerance
        assert second.restored.conditions[0].id == 7  # everything else restored
        assert any(f"offset_calibrations row {bad_id}: offsets_c" in m and "31 values" in m for m in said), (
            said
        )
        with repo.session_scope(second.session_factory) as s:
            assert s.scalars(select(OffsetCalibrationRow.id)).all().count(bad_id) == 1  # nothing lost
    finally:
        second.close()


@pytest.mark.parametrize(
    ("field", "value", "why"),
    [
        ("sd_c", [0.01] * 31 + [-0.01], "sd_c: every channel needs a finite 1σ > 0"),
        ("sd_c", [0.01] * 31 + [None], "sd_c: every channel needs a finite 1σ > 0"),
        ("offsets_c", [0.1] * 31 + ["x"], "offsets_c: channel 32: 'x'"),
        ("offsets_c", {"1": 0.1}, "offsets_c: expected a list of 32 values (one per channel), got dict"),
        ("source", "guess", "source: 'guess' not in"),
        ("samples", 0, "samples: need an integer >= 1"),
        ("t_to", T0 - timedelta(hours=2), "t_to: "),
    ],
)
def test_each_bad_field_is_named(field: str, value: object, why: str) -> None:
    row = OffsetCalibrationRow(
        id=3,
        t_from=T0 - timedelta(hours=1),
        t_to=T0,
        source="auto",
        samples=30,
        offsets_c=[0.1] * 32,
        sd_c=[0.01] * 32,
    )
    setattr(row, field, value)
    with pytest.raises(
        StoredCalibrationError,
        match="offset_calibrations row 3: " + why.replace("(", r"\(").replace(")", r"\)"),
    ):
        calibration_from_row(row)


def test_a_record_refuses_a_naive_time_or_mismatched_lengths() -> None:
    naive = datetime(2026, 3, 1, 6, 0)
    with pytest.raises(RecordError, match="t_to: naive"):
        Calibration(
            t_from=T0, t_to=naive, source="auto", samples=3, offsets_c=np.array([0.1]), sd_c=np.array([0.01])
        )
    with pytest.raises(RecordError, match="sd_c: expected 2 values"):
        Calibration(
            t_from=T0,
            t_to=T0,
            source="auto",
            samples=3,
            offsets_c=np.array([0.1, 0.2]),
            sd_c=np.array([0.01]),
        )
