"""TimelineSource: simulated time from an injected clock, interpolation and hold, validation."""

from __future__ import annotations

import numpy as np
import pytest

from drivers.sim.source import ArrayTimeline, TimelineError, TimelineSource
from tests.sim.simhelpers import FakeClock, ramp_timeline


def test_sim_time_is_speedup_times_wall_time() -> None:
    clock = FakeClock()
    src = TimelineSource(ramp_timeline(), speedup=20.0, clock=clock)
    src.start()
    clock.advance(2.5)
    assert src.sim_time_s() == pytest.approx(50.0)


def test_interpolates_between_rows_and_holds_status() -> None:
    run = ramp_timeline()
    clock = FakeClock()
    src = TimelineSource(run, speedup=10.0, clock=clock)
    src.start()
    clock.advance(2.5)  # sim 25 s of 100 s: a quarter of the way
    snap = src.now()
    expected = run.temps_c[0] + 0.25 * (run.temps_c[1] - run.temps_c[0])
    np.testing.assert_allclose(snap.temps_c, expected)
    assert snap.speed_rpm == pytest.approx(2000.0)
    assert snap.torque_nm == pytest.approx(3.0)
    assert snap.index == 0


def test_hold_mode_returns_recorded_rows_exactly() -> None:
    run = ramp_timeline()
    src = TimelineSource(run, mode="hold", clock=FakeClock())
    np.testing.assert_array_equal(src.at(99.9).temps_c, run.temps_c[0])
    np.testing.assert_array_equal(src.at(100.0).temps_c, run.temps_c[1])


def test_past_the_end_holds_last_row_or_wraps_when_looping() -> None:
    run = ramp_timeline()
    assert TimelineSource(run, clock=FakeClock()).at(150.0).speed_rpm == pytest.approx(5000.0)
    assert TimelineSource(run, loop=True, clock=FakeClock()).at(125.0).speed_rpm == pytest.approx(2000.0)


def test_finished_after_last_row() -> None:
    clock = FakeClock()
    src = TimelineSource(ramp_timeline(), speedup=100.0, clock=clock)
    src.start()
    assert not src.finished()
    clock.advance(1.01)
    assert src.finished()


def test_bad_timelines_name_the_array() -> None:
    run = ramp_timeline()
    bad_times = ArrayTimeline(
        np.array([0.0, 0.0]), run.temps_c, run.ambient_c, run.speed_rpm, run.torque_nm, run.status
    )
    with pytest.raises(TimelineError, match="times_s"):
        TimelineSource(bad_times)
    bad_speed = ArrayTimeline(run.times_s, run.temps_c, run.ambient_c, np.zeros(3), run.torque_nm, run.status)
    with pytest.raises(TimelineError, match="speed_rpm"):
        TimelineSource(bad_speed)
    with pytest.raises(TimelineError, match="speedup"):
        TimelineSource(run, speedup=0.0)


def test_extend_appends_rows_that_play_on_past_the_old_end() -> None:
    """``chtc demo`` grows its timeline while it plays: past the old last row the new rows are served, not
    the old last row held."""
    run = ramp_timeline()  # rows at 0 and 100 s
    clock = FakeClock()
    src = TimelineSource(run, speedup=1.0, clock=clock)
    src.start()
    later = ArrayTimeline(
        times_s=np.array([200.0]),
        temps_c=run.temps_c[1:] + 10.0,
        ambient_c=run.ambient_c[1:],
        speed_rpm=np.array([5000.0]),
        torque_nm=run.torque_nm[1:],
        status=run.status[1:],
    )
    src.extend(later)
    clock.advance(150.0)  # halfway between the old last row and the new one
    snap = src.now()
    np.testing.assert_allclose(snap.temps_c, run.temps_c[1] + 5.0)
    assert snap.speed_rpm == pytest.approx(0.5 * (run.speed_rpm[1] + 5000.0))
    assert src.duration_s == pytest.approx(200.0) and not src.finished()
    with pytest.raises(TimelineError, match="after the last row"):
        src.extend(later)  # the same rows again: not after the last one
