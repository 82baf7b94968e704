"""A database unreachable at start-up (issue 25, item 4): said once as a warning, also under ``--quiet``; the
ids stay small when the database answers before the first one is issued."""

from __future__ import annotations

import asyncio
import logging
from datetime import UTC, datetime

from model.plant import Segment
from service.contracts.records import ConditionStart
from service.core.events import IdsKnown, Log, SampleReceived, Store
from service.core.machine import ServiceCore
from service.host.persistence import fallback_restored, open_persistence
from service.settings import Settings
from tests.engine_config import PER_CONDITION_10_20, product_core

from .conftest import plant_run, samples_of

# the product's defaults but the per-condition protocol with 10-min windows (PER_CONDITION_10_20: these tests'
# timings) and without the sensor offset calibration
CFG = product_core(identification={**PER_CONDITION_10_20, "offset_calibration": False})
UNREACHABLE = "postgresql+psycopg://u:p@127.0.0.1:1/x"  # nothing listens on port 1: refused at once


def test_an_unreachable_database_is_a_warning_said_once(caplog) -> None:  # type: ignore[no-untyped-def]
    """It went only to the progress lines, which ``chtc demo --quiet`` silences: the demo started silently."""
    db = Settings().database.model_copy(update={"url": UNREACHABLE})
    said: list[str] = []
    with caplog.at_level(logging.INFO, logger="service.host.persistence"):
        p = open_persistence(db, migrate=True, on_event=said.append)
        try:

            async def retry_a_few_times() -> None:
                task = asyncio.ensure_future(p.ensure_open(retry_s=0.01))
                await asyncio.sleep(0.3)
                task.cancel()

            asyncio.run(retry_a_few_times())
        finally:
            p.close()
    logged = [r for r in caplog.records if r.name == "service.host.persistence"]
    assert [r.levelno for r in logged] == [logging.WARNING], [r.getMessage() for r in logged]
    text = logged[0].getMessage()
    assert text.startswith("db: not available at start-up (database not reachable") and "ids start at" in text
    assert said == []  # not said twice (chtc run logs its progress lines too)


def test_a_database_answering_late_tells_its_next_ids(tmp_path) -> None:  # type: ignore[no-untyped-def]
    from service.store.engine import create_db_engine, make_session_factory
    from service.store.migrate import upgrade
    from service.store.repository import session_scope, write_records

    url = f"sqlite:///{tmp_path / 'late.db'}"
    db = Settings().database.model_copy(update={"url": url})
    p = open_persistence(db, migrate=False)  # no schema yet: not available at start-up
    told: list[tuple[int, int]] = []
    try:
        assert not p.restored_from_db and p.restored.next_condition_id > 10**12
        engine = create_db_engine(url)
        upgrade(engine)  # an operator migrates; an earlier run's condition 41 is in the table
        t = datetime(2026, 3, 2, tzinfo=UTC)
        with session_scope(make_session_factory(engine)) as session:
            old = ConditionStart(id=41, started_at=t, speed_rpm=0.0, torque_nm=0.0, ambient_c=22.0)
            write_records(session, [old])
        engine.dispose()
        p.on_open = lambda c, i: told.append((c, i))
        asyncio.run(asyncio.wait_for(p.ensure_open(retry_s=0.01), timeout=30))
    finally:
        p.close()
    assert told == [(42, 1)]


def _condition_ids(core: ServiceCore, events: list[SampleReceived]) -> list[int]:
    return [
        ins.record.id
        for ev in events
        for ins in core.handle(ev)
        if isinstance(ins, Store) and isinstance(ins.record, ConditionStart)
    ]


def test_ids_continue_from_the_database_unless_one_was_issued(loaded_model) -> None:  # type: ignore[no-untyped-def]
    """Before: ids like 1795761900000 for the whole run even when the database answered seconds later."""
    run = plant_run([Segment(400.0, 0.0, 0.0, 22.0), Segment(300.0, 3000.0, 5.0, 22.0)], seed=5)
    events = [SampleReceived(f"sample-{n}", s) for n, s in enumerate(samples_of(run), start=1)]
    base = fallback_restored(now_s=1_795_761_900).next_condition_id

    early = ServiceCore(CFG, model=loaded_model, restored=fallback_restored(now_s=1_795_761_900))
    said = early.handle(IdsKnown("ids-1", 42, 7))
    assert [type(i) for i in said] == [Log] and "continue from the stored ones" in said[0].message
    assert _condition_ids(early, events) == [42, 43]

    late = ServiceCore(CFG, model=loaded_model, restored=fallback_restored(now_s=1_795_761_900))
    first = _condition_ids(late, events[:20])
    said = late.handle(IdsKnown("ids-1", 42, 7))  # an id was issued: this run keeps the base
    assert first == [base] and "keeps them" in said[0].message
    assert _condition_ids(late, events[20:]) == [base + 1]
