"""Combined mode (``identification.mode = "combined"``, issue 17) through the real core and shell over the
virtual plant (its own mesh and truth): the per-condition identification of a held condition serves while
the condition holds, the map's H at the current speed elsewhere (right after a change, at short
conditions); the live state follows the served H; both job kinds share the worker and the job book."""

from __future__ import annotations

import numpy as np
import pytest

from benchmarks.chain import last_per_condition
from benchmarks.identmode import served_in_order
from model.geometry import load_spindle
from model.plant import Segment, VirtualPlant
from service.contracts.verdict import ChtcStatus
from service.core.jobbook import MAP_METHOD
from service.core.maptrack import into_box
from service.host.persistence import open_persistence
from service.identify.prior import ServedMapPrior
from service.settings import Settings

from .conftest import inline_service, samples_of

pytestmark = pytest.mark.slow  # the combined-mode service over a duty cycle (~35 s fixture at load 8)

# 5 min idle; 3000 rpm held 20 min (per-condition at 7 and 20 min; the map's first fit after 10 min of
# data); 4500 rpm for 4 min (shorter than the first schedule entry: the map's only); 2000 rpm held 12 min
SETTINGS = Settings(identification={"mode": "combined"})  # type: ignore[arg-type]  # the default, named
PROFILE = (
    Segment(300.0, 0.0, 0.0, 20.0),
    Segment(1200.0, 3000.0, 6.0, 20.0),
    Segment(240.0, 4500.0, 9.0, 20.0),
    Segment(720.0, 2000.0, 4.0, 20.0),
)


@pytest.fixture(scope="module")
def combined(loaded_model):
    """The profile through the service in combined mode; per sample: (speed, ambient, /chtc, view)."""
    run = VirtualPlant(load_spindle(), seed=11).run(list(PROFILE), dt_s=10.0)
    samples = samples_of(run)
    svc, clock = _service(loaded_model, samples)
    seen = []
    for s in samples:
        clock.at_least(s.t)
        svc.on_sample(s)
        seen.append((s.speed_rpm, s.ambient_c, svc.chtc(), svc.view, np.array(svc.core.live_h)))
    return svc, seen, samples


def _service(model, samples, *, writer=None, restored=None):
    return inline_service(model, SETTINGS, samples, writer=writer, restored=restored)


def _segment_of(k: int) -> int:
    t = 10.0 * k
    ends = np.cumsum([seg.duration_s for seg in PROFILE])
    return min(int(np.searchsorted(ends, t, side="right")), len(PROFILE) - 1)


def test_both_kinds_run_and_share_the_job_book(combined) -> None:
    svc, _, _ = combined
    assert svc.identification_mode() == "combined"
    records = svc.view.records
    methods = {r.method for r in records if r.outcome == "ok"}
    assert MAP_METHOD in methods and len(methods) == 2, methods
    jobs = svc.view.jobs
    assert len(jobs) == len({r.id for r in records}) >= 6  # one key per launched job, none reused
    assert svc.chtc_map() is not None


def test_held_condition_serves_its_per_condition_h_and_the_map_elsewhere(combined) -> None:
    svc, seen, _ = combined
    served_prior = ServedMapPrior(svc.core.model.spec, svc.core.model.ref.h_box)
    kinds: dict[int, set[str]] = {0: set(), 1: set(), 2: set(), 3: set()}
    for k, (speed, ambient, snap, view, live_h) in enumerate(seen):
        if snap is None:
            continue
        rec = snap.record
        seg = _segment_of(k)
        # the detector's median (3 samples) sees a change from the second sample at the new speed on
        if seg == _segment_of(k - 2):
            kinds[seg].add(rec.method)
        if rec.method != MAP_METHOD:
            # only the current, stable condition's own per-condition identification serves
            assert view.condition is not None and rec.condition.id == view.condition.id
            assert view.condition.state.value == "stable" and not view.map_serves
            np.testing.assert_allclose(live_h, rec.h)  # the live state uses the served H
        else:
            assert view.map_serves and view.speed_map is not None
            h, lo, hi = view.speed_map.h_at([speed], ambient)
            # the map's information at the current speed on the cold physics prior (service.identify.prior)
            prior = served_prior.at(view.speed_map, level_sd=0.0, speed_rpm=speed, ambient_c=ambient)
            np.testing.assert_allclose(snap.h, np.exp(prior.log_mean))
            assert np.all((lo[0] <= snap.h) & (snap.h <= hi[0]))  # inside the map's own band
            if view.speed_map is seen[k - 1][3].speed_map:  # a fit that came back now: from the next sample
                # within the map's 50-rpm live bin, clipped into the reduced model's box (issue 40)
                inside, _ = into_box(h[0], lo[0], hi[0], svc.core.model.ref.h_box)
                np.testing.assert_allclose(live_h, inside, rtol=0.02)
    assert kinds[2] == {MAP_METHOD}, kinds  # 4 min at 4500 rpm: the map's only
    for seg in (1, 3):  # held conditions: the map first, then their own per-condition identification
        assert kinds[seg] == {MAP_METHOD, SETTINGS.experimental.method}, (seg, kinds)


def test_benches_take_the_served_identification(combined) -> None:
    svc, _, _ = combined
    records = list(reversed(svc.view.records))  # oldest first
    served = served_in_order(records)
    held: set[int] = set()
    for r in served:  # no map fit served at a condition after its own per-condition identification
        if r.method != MAP_METHOD:
            held.add(r.condition.id)
        assert r.method != MAP_METHOD or r.condition.id not in held
    assert held
    dropped = [r for r in records if r.outcome == "ok" and r not in served]
    assert dropped and all(r.method == MAP_METHOD for r in dropped)
    last = last_per_condition(records)
    assert last[3000.0].method != MAP_METHOD and last[4500.0].method == MAP_METHOD


def test_restart_restores_the_map_when_a_per_condition_identification_was_last(
    combined, tmp_path, loaded_model
) -> None:
    _, seen, samples = combined
    # up to the sample after which the 2000-rpm condition's own per-condition identification came back
    n = next(
        k + 1
        for k, (_, _, snap, _, _) in enumerate(seen)
        if _segment_of(k) == 3 and snap is not None and snap.record.method != MAP_METHOD
    )
    db = SETTINGS.database.model_copy(update={"url": f"sqlite:///{tmp_path / 'chtc.db'}"})
    first = open_persistence(db, migrate=True)
    svc, clock = _service(loaded_model, samples[:n], writer=first.sink)
    for s in samples[:n]:
        clock.at_least(s.t)
        svc.on_sample(s)
    newest = svc.view.records[0]
    newest_map = next(r for r in svc.view.records if r.method == MAP_METHOD and r.outcome == "ok")
    assert newest.method != MAP_METHOD
    first.close()

    second = open_persistence(db, migrate=True)
    restored = second.restored
    assert restored.last is not None and restored.last.id == newest.id
    assert restored.map_last is not None and restored.map_last.id == newest_map.id
    assert restored.speed_map is not None and restored.speed_map.restored
    assert restored.speed_map.identification_id == newest_map.id
    svc2, _ = _service(loaded_model, samples[n:], restored=restored)
    view = svc2.view
    assert view.map_serves and view.current is not None and view.current.id == newest_map.id
    assert view.current_from_restore
    snap = svc2.chtc()
    assert snap is not None and snap.status is ChtcStatus.STALE and snap.record.id == newest_map.id
    second.close()


def test_no_served_bound_beyond_ten_times_the_search_box(combined) -> None:
    """Issue 26: /chtc served H1 [0.0, 498406011]; a MAP fit (per-condition) and the map on the cold prior
    (map-served) keep every bound within 10x the search box, and a prior-dominated H is never identified."""
    svc, seen, _ = combined
    lo_box, hi_box = svc.core.model.ref.h_box
    snaps = [snap for _, _, snap, _, _ in seen if snap is not None]
    assert snaps
    for snap in snaps:
        assert np.all(np.isfinite(snap.ci95_hi)) and np.all(snap.ci95_hi <= 10 * hi_box)
        assert np.all(snap.ci95_lo >= lo_box / 10)
        assert not np.any(snap.identified & snap.prior_dominated)
    fits = [r for r in svc.view.records if r.outcome == "ok" and r.method != MAP_METHOD]
    assert fits and all(
        "prior" in (r.data.diagnostics or {}) for r in fits
    )  # per-condition fits are MAP fits


def test_the_served_map_prior_keeps_its_last_answer(combined) -> None:
    """``/chtc`` asks for the map's H at the newest sample's speed and ambient on every request until the
    next sample: the last answer is kept (the same object), and any other argument computes afresh."""
    svc, seen, _ = combined
    m = next(view.speed_map for *_, view, _ in reversed(seen) if view.speed_map is not None)
    served_prior = ServedMapPrior(svc.core.model.spec, svc.core.model.ref.h_box)
    a = served_prior.at(m, level_sd=0.0, speed_rpm=4000.0, ambient_c=21.0)
    assert served_prior.at(m, level_sd=0.0, speed_rpm=4000.0, ambient_c=21.0) is a
    b = served_prior.at(m, level_sd=0.0, speed_rpm=5000.0, ambient_c=21.0)
    assert b is not a and not np.allclose(b.log_mean, a.log_mean)
    again = served_prior.at(m, level_sd=0.0, speed_rpm=4000.0, ambient_c=21.0)
    fresh = ServedMapPrior(svc.core.model.spec, svc.core.model.ref.h_box)
    expected = fresh.at(m, level_sd=0.0, speed_rpm=4000.0, ambient_c=21.0)
    np.testing.assert_array_equal(again.log_mean, expected.log_mean)
    np.testing.assert_array_equal(again.log_cov, expected.log_cov)
