"""The service core is a pure state machine (issue 14, item 1): events in, instructions out, no lock, no
database code, the same instructions for the same events, and event ids carried into the stored records."""

from __future__ import annotations

import asyncio
import dataclasses
import subprocess
import sys
import threading
from collections.abc import Callable
from datetime import UTC, datetime

import numpy as np
import pytest

from model.plant import Segment
from service.contracts.errors import NotReadyError
from service.contracts.records import IdentificationData
from service.contracts.snapshots import JobState
from service.core.events import (
    Event,
    Instruction,
    JobOutcomeReceived,
    Launch,
    Log,
    ManualAccepted,
    ManualRequested,
    Rejected,
    RejectKind,
    SampleReceived,
    Store,
)
from service.core.machine import ServiceCore
from service.identify.worker import run_job
from service.modelload import LoadedModel
from service.shell.service import SoftSensorService
from tests.engine_config import PER_CONDITION_10_20, product_core

from .conftest import plant_run, samples_of
from .drive import outcome_event

# the product's defaults but the per-condition protocol with 10-min windows (PER_CONDITION_10_20: these tests'
# timings) and without the sensor offset calibration (its baseline would add events the tests do not expect)
CFG = product_core(identification={**PER_CONDITION_10_20, "offset_calibration": False})


def test_importing_the_core_loads_no_database_code() -> None:
    code = (
        "import sys, service.core.machine, service.core.events, service.core.view\n"
        "print(sorted(m for m in sys.modules if m.split('.')[0] in ('sqlalchemy', 'alembic')))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]", out.stdout


def test_the_core_holds_no_lock_and_no_callbacks(loaded_model: LoadedModel) -> None:
    core = ServiceCore(CFG, model=loaded_model)
    lock_types = (type(threading.Lock()), type(threading.RLock()))
    assert not [k for k, v in vars(core).items() if isinstance(v, lock_types)]
    assert not [k for k, v in vars(core).items() if callable(v) and not isinstance(v, type)]
    assert not hasattr(core, "lock") and not hasattr(ServiceCore, "_manual_reason")


@pytest.fixture(scope="module")
def two_conditions():  # type: ignore[no-untyped-def]
    """An idle condition (the live state converges in ~5 min; its job 10 min later is skipped), then 3000 rpm
    (identified at 10 min)."""
    run = plant_run([Segment(1000.0, 0.0, 0.0, 22.0), Segment(700.0, 3000.0, 5.0, 22.0)], seed=5)
    return samples_of(run)


def _drive(
    core: ServiceCore, events: list[Event], run: Callable[[Launch], JobOutcomeReceived] | None
) -> tuple[list[Event], list[Instruction]]:
    """Hand ``events`` to ``core``; with ``run``, each launched job's outcome follows its event."""
    seen: list[Event] = []
    out: list[Instruction] = []
    pending = list(events)
    while pending:
        ev = pending.pop(0)
        seen.append(ev)
        for ins in core.handle(ev):
            out.append(ins)
            if run is not None and isinstance(ins, Launch):
                pending.insert(0, run(ins))
    return seen, out


def ln_t(launch: Launch) -> datetime:
    """An offline job finishes at its window's end (no wall time passes)."""
    return datetime.fromtimestamp(float(launch.request.window.times_s[-1]), tz=UTC)


def _fingerprint(ins: Instruction) -> object:
    if isinstance(ins, Launch):
        r = ins.request
        w = r.window
        arrays = (w.times_s, w.measured_c, w.mask, np.asarray(r.t0_c))
        return ("launch", ins.event_id, ins.job_key, r.job_id, r.warm_start, *(a.tobytes() for a in arrays))
    return repr(ins)


def test_same_events_give_the_same_instructions_on_a_fresh_core(loaded_model, two_conditions) -> None:  # type: ignore[no-untyped-def]
    events: list[Event] = [SampleReceived(f"sample-{n}", s) for n, s in enumerate(two_conditions, start=1)]
    events.insert(130, ManualRequested("manual-1", "too early"))
    first = ServiceCore(CFG, model=loaded_model)

    def run(launch: Launch) -> JobOutcomeReceived:
        return outcome_event(first, run_job(loaded_model, launch.request), two_conditions[-1].t)

    seen, out1 = _drive(first, events, run)
    _, out2 = _drive(ServiceCore(CFG, model=loaded_model), seen, None)
    assert sum(isinstance(i, Launch) for i in out1) == 1
    assert [_fingerprint(i) for i in out1] == [_fingerprint(i) for i in out2]
    refused = [i for i in out1 if isinstance(i, Rejected)]
    assert len(refused) == 1 and refused[0].event_id == "manual-1" and refused[0].kind is RejectKind.NOT_READY


def test_event_ids_are_carried_into_the_stored_identifications(
    loaded_model, two_conditions, tmp_path
) -> None:  # type: ignore[no-untyped-def]
    from service.store import repository as repo
    from service.store.engine import create_db_engine, make_session_factory
    from service.store.migrate import upgrade

    core = ServiceCore(CFG, model=loaded_model)
    events: list[Event] = [SampleReceived(f"sample-{n}", s) for n, s in enumerate(two_conditions, start=1)]
    _, out = _drive(core, events, lambda ln: outcome_event(core, run_job(loaded_model, ln.request), ln_t(ln)))
    (launch,) = [i for i in out if isinstance(i, Launch)]
    idents = [i for i in out if isinstance(i, Store) and isinstance(i.record, IdentificationData)]
    skipped, done = (i.record for i in idents)
    assert skipped.outcome == "skipped" and done.outcome == "ok"
    # a job ended at once: started and finished by the sample that made it due
    (skip_store,) = [i for i in idents if i.record is skipped]
    assert skipped.started_by_event == skipped.finished_by_event == skip_store.event_id
    assert done.started_by_event == launch.event_id and launch.event_id.startswith("sample-")
    assert done.finished_by_event == f"outcome-{launch.request.job_id}"
    # the log lines of the job carry the same ids
    said = {i.event_id for i in out if isinstance(i, Log) and launch.job_key in i.message}
    assert said == {done.started_by_event, done.finished_by_event}

    eng = create_db_engine(f"sqlite:///{tmp_path / 'chtc.db'}")
    upgrade(eng)
    factory = make_session_factory(eng)
    with repo.session_scope(factory, "write") as s:
        repo.write_records(s, [i.record for i in out if isinstance(i, Store)])
    with repo.session_scope(factory, "read") as s:
        rows = {r.id: repo.get_identification(s, r.id).diagnostics for r in (skipped, done)}
    assert rows[done.id]["events"] == {"started_by": launch.event_id, "finished_by": done.finished_by_event}
    assert rows[done.id]["rmse_per_sensor"]  # the other diagnostics are still there
    assert rows[skipped.id] == {
        "events": {"started_by": skip_store.event_id, "finished_by": skip_store.event_id}
    }
    eng.dispose()


def test_a_manual_request_carries_its_reason_into_the_job_and_the_record(
    loaded_model, two_conditions
) -> None:  # type: ignore[no-untyped-def]
    core = ServiceCore(CFG, model=loaded_model)
    events: list[Event] = [SampleReceived(f"sample-{n}", s) for n, s in enumerate(two_conditions, start=1)]
    _drive(core, events, lambda ln: outcome_event(core, run_job(loaded_model, ln.request), ln_t(ln)))
    out = core.handle(ManualRequested("manual-7", "operator check"))
    (launch,) = [i for i in out if isinstance(i, Launch)]
    (accepted,) = [i for i in out if isinstance(i, ManualAccepted)]
    assert {i.event_id for i in out} == {"manual-7"}
    assert accepted.job.reason == "operator check" and accepted.job.state is JobState.RUNNING
    assert accepted.job.job_id == launch.job_key
    (busy,) = core.handle(ManualRequested("manual-8", "again"))
    assert isinstance(busy, Rejected) and busy.kind is RejectKind.BUSY
    done = core.handle(outcome_event(core, run_job(loaded_model, launch.request), ln_t(launch)))
    (rec,) = [i.record for i in done if isinstance(i, Store) and isinstance(i.record, IdentificationData)]
    assert rec.reason == "operator check" and rec.started_by_event == "manual-7"
    assert core.view().jobs[launch.job_key].state is JobState.DONE


def test_the_shell_publishes_immutable_views(loaded_model, two_conditions) -> None:  # type: ignore[no-untyped-def]
    core = ServiceCore(CFG, model=loaded_model)
    svc = SoftSensorService(core, worker=None, run_job=lambda req: run_job(loaded_model, req))
    before = svc.view
    for s in two_conditions[:100]:
        svc.on_sample(s)
    after = svc.view
    assert before.newest is None and before.records == ()  # an old view does not change
    assert after.newest is not None and after.newest.t == two_conditions[99].t
    assert [r.outcome for r in after.records] == ["skipped"]
    with pytest.raises(dataclasses.FrozenInstanceError):
        after.current = None  # type: ignore[misc]
    with pytest.raises(TypeError):
        after.jobs["job-9"] = after.jobs["job-1"]  # type: ignore[index]
    assert not after.newest.temps_c.flags.writeable
    assert after.live is not None and not after.live.field_c.flags.writeable


def test_an_api_thread_request_is_handled_on_the_event_loop(loaded_model) -> None:  # type: ignore[no-untyped-def]
    core = ServiceCore(CFG, model=loaded_model)
    svc = SoftSensorService(core, worker=None)
    threads: list[int] = []
    handle = core.handle

    def recording(event: Event) -> list[Instruction]:
        threads.append(threading.get_ident())
        return handle(event)

    core.handle = recording  # type: ignore[method-assign]

    async def main() -> str:
        await svc.start()
        try:
            with pytest.raises(NotReadyError) as err:
                await asyncio.to_thread(svc.request_identification, "from a thread")
            return str(err.value)
        finally:
            await svc.close()

    message = asyncio.run(main())
    assert "no samples yet" in message
    assert len(threads) == 1  # the request, handled on the loop's thread
    assert threads[0] == threading.get_ident()  # asyncio.run ran the loop on this thread
