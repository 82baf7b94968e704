"""After a restart the service serves the last stored H at once, marked stale, and resumes ids and warm
starts from the database (real SQLite, migrated with Alembic)."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta

import numpy as np

from model.plant import Segment
from service.core import ServiceCore
from service.history import RingHistory
from service.interface import ChtcStatus
from service.offline import run_offline
from service.persistence import open_persistence
from service.runtime import core_config
from service.service import SoftSensorService
from service.settings import Settings

from .conftest import plant_run, ring_of, samples_of


def test_restart_restores_last_h_stale_with_ids_and_history(tmp_path, loaded_model):
    s = Settings()
    db = s.database.model_copy(update={"url": f"sqlite:///{tmp_path / 'chtc.db'}"})
    cfg = core_config(s)
    run = plant_run([Segment(1300.0, 3000.0, 5.0, 22.0)], seed=2)
    first = open_persistence(db, migrate=True)
    assert first.restored_from_db and first.restored.last is None
    result = run_offline(samples_of(run), model=loaded_model, config=cfg, sink=first.sink)
    ok = [r for r in result.records if r.outcome == "ok"]
    assert len(ok) == 2  # at 10 and 20 min
    first.close()

    second = open_persistence(db, migrate=True)
    restored = second.restored
    assert restored.last is not None and restored.last.id == ok[-1].id
    np.testing.assert_allclose(restored.last.h, ok[-1].h)
    assert restored.next_identification_id == max(r.id for r in result.records) + 1
    assert restored.next_condition_id == ok[-1].condition.id + 1
    assert [p.condition_id for p in restored.history] == [ok[-1].condition.id]
    assert restored.conditions[0].speed_rpm == ok[-1].condition.speed_rpm

    now = [datetime.now(UTC)]
    ring = ring_of()
    core = ServiceCore(
        cfg, model=loaded_model, history=RingHistory(ring), sink=second.sink, restored=restored
    )
    svc = SoftSensorService(
        core, worker=None, writer=second.sink, session_factory=second.session_factory, clock=lambda: now[0]
    )
    snap = svc.chtc()
    assert snap is not None and snap.status is ChtcStatus.STALE
    assert snap.identification_id == ok[-1].id and snap.identified_at == ok[-1].finished_at
    np.testing.assert_allclose(snap.h, ok[-1].h)
    assert svc.condition().id == ok[-1].condition.id
    # samples of the same condition arrive: the stored condition continues (no new condition), H stays stale
    later = samples_of(run, t0=now[0].timestamp())[:5]
    for smp in later:
        ring.append(smp)
        core.ingest(smp)
    now[0] = later[-1].t + timedelta(seconds=1)
    assert svc.condition().id == ok[-1].condition.id
    assert svc.chtc().status is ChtcStatus.STALE
    page = svc.list_identifications(since=None, until=None, limit=10, offset=0)
    assert page.items[0].id == ok[-1].id and page.total == len(result.records)
    second.close()
