"""A restored state dated after the first new sample (issue 41 section 3): a clock stepped back (a demo re-run
on its own database, NTP, a replaced controller PC) makes the database hold a live-state checkpoint,
conditions and an identification from the "future". None is resumed (said once in the log), the state
starts from its prior, and the core raises on no time it has not seen.

Data: the virtual plant through the real core (jobs inline with the worker's own function).
"""

from __future__ import annotations

from dataclasses import replace

import pytest

from model.plant import Segment
from service.contracts.records import ConditionStart
from service.core.config import Restored
from service.core.events import Log, Store
from service.core.machine import ServiceCore
from service.core.restorecut import cut_future
from service.host.runtime import core_config
from service.identify.detector import OperatingPoint
from service.identify.scheduler import PastResult
from tests.modes import per_condition

from .conftest import plant_run, samples_of
from .drive import feed_and_run

FIRST_K = 150  # the first run: 25 min (5 min idle, then 3000 rpm)


@pytest.fixture(scope="module")
def samples():  # type: ignore[no-untyped-def]
    run = plant_run([Segment(300.0, 0.0, 0.0, 22.0), Segment(1500.0, 3000.0, 5.0, 22.0)], seed=5)
    return samples_of(run)


def _restored(core: ServiceCore, model_version: str) -> Restored:
    """What the database holds after the first run: its conditions, its last identification, its live
    state's checkpoint."""
    v = core.view()
    rec = v.current
    assert rec is not None
    c = rec.condition
    past = PastResult(
        condition_id=c.id,
        point=OperatingPoint(speed_rpm=c.speed_rpm, torque_nm=c.torque_nm, ambient_c=c.ambient_c),
        h=tuple(float(x) for x in rec.h),
    )
    return Restored(
        last=rec,
        history=(past,),
        conditions=v.conditions,
        next_condition_id=max(c.id for c in v.conditions) + 1,
        next_identification_id=max(r.id for r in v.records) + 1,
        live=core._p.live.checkpoint(model_version),
    )


def test_a_state_from_the_future_is_not_resumed_and_nothing_raises(loaded_model, samples) -> None:  # type: ignore[no-untyped-def]
    """The same samples again from the start, on what the first run stored: every restored item is dated
    after the first new sample. The core handles the whole run (its condition change included) without an
    error, says once why it did not resume, starts the live state at the first new sample, serves no
    restored H, and numbers its conditions after the stored ones."""
    cfg = core_config(per_condition())
    first = ServiceCore(cfg, model=loaded_model)
    feed_and_run(first, loaded_model, samples[:FIRST_K])
    restored = _restored(first, loaded_model.version)
    assert [c.id for c in restored.conditions] == [2, 1]

    again = ServiceCore(cfg, model=loaded_model, restored=restored)
    out = feed_and_run(again, loaded_model, samples[:60])  # the 3000-rpm start at minute 5 included
    lines = [i.message for i in out if isinstance(i, Log)]
    said = [m for m in lines if "after the first sample" in m]
    assert any(m.startswith("live state not resumed") for m in said), lines[:5]
    assert any("condition(s) dated after" in m for m in said) and any("identification(s)" in m for m in said)
    assert not any("resumed from its checkpoint" in m for m in lines)
    # the first condition (at rest since the first sample) is not after it: it continues; the second is not
    assert "resumed condition 1 (0 rpm) from the database" in lines
    assert not any(m.startswith("resumed condition 2") for m in lines)
    assert len(said) == 3  # once each
    view = again.view()
    assert view.live is not None and view.live.started_at == samples[0].t.timestamp()
    assert view.current is None or not view.current_from_restore
    new_ids = [r.record.id for r in out if isinstance(r, Store) and isinstance(r.record, ConditionStart)]
    assert new_ids and min(new_ids) == restored.next_condition_id
    assert all(c.since <= samples[59].t for c in view.conditions)


def test_cut_future_keeps_what_is_not_after_the_first_sample(loaded_model, samples) -> None:  # type: ignore[no-untyped-def]
    """A restore dated before the first sample is resumed unchanged (no note)."""
    cfg = core_config(per_condition())
    first = ServiceCore(cfg, model=loaded_model)
    feed_and_run(first, loaded_model, samples[:FIRST_K])
    restored = _restored(first, loaded_model.version)
    same, notes = cut_future(restored, samples[FIRST_K].t.timestamp())
    assert same is restored and notes == []
    assert restored.live is not None
    cut, notes = cut_future(replace(restored, last=None), restored.live.t - 1.0)
    assert cut.live is None and len(notes) == 1
