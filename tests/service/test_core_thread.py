"""The core off the event loop (issue 30): the core thread handles events in order, the published view is
immutable, a backlog past its limit is served as ``core_behind`` (and /healthz says so), the event loop's lag
is measured and degrades /healthz past its limit (the demo's simulated devices, in a process of their own:
test_rig_process.py). Driven deterministically: a gate holds the core thread, an injected lag source stands
for the loop."""

from __future__ import annotations

import asyncio
import dataclasses
import threading
from datetime import timedelta

import numpy as np
import pytest

from drivers.ringbuffer import Sample
from model.plant import Segment
from service.contracts.health import DeviceStatus
from service.contracts.verdict import ChtcStatus, DataCode, DataProblem, Reason
from service.core.events import Event, IdsKnown, Instruction, SampleReceived
from service.core.machine import ServiceCore
from service.host.runtime import core_config
from service.settings import Settings
from service.shell.corethread import CoreThread
from service.shell.looplag import LoopLagMonitor
from service.shell.service import SoftSensorService
from simulator.served import ManualClock

from .conftest import plant_run, samples_of


@pytest.fixture(scope="module")
def samples() -> list[Sample]:
    return samples_of(plant_run([Segment(200.0, 0.0, 0.0, 22.0)], seed=3))


def _sample_event(i: int, s: Sample) -> SampleReceived:
    return SampleReceived(f"sample-{i}", s)


class GatedThread(CoreThread):
    """The real core thread whose step waits at a gate (the core "busy") until ``gate.set()``."""

    def __init__(self, **kw: object) -> None:
        super().__init__(**kw)  # type: ignore[arg-type]
        self.gate = threading.Event()
        self.entered = threading.Event()

    def start(self, step, on_change) -> None:  # type: ignore[no-untyped-def]
        def gated(event: Event) -> list[Instruction]:
            self.entered.set()
            self.gate.wait(30.0)
            return step(event)

        super().start(gated, on_change)


def test_core_thread_handles_events_in_order_off_the_callers_thread(samples: list[Sample]) -> None:
    seen: list[tuple[str, int]] = []

    def step(event: Event) -> list[Instruction]:
        seen.append((event.event_id, threading.get_ident()))
        return []

    runner = CoreThread(capacity=100)
    runner.start(step, lambda: None)
    for i, s in enumerate(samples[:20]):
        runner.post(_sample_event(i, s))
    reply = runner.call(IdsKnown("ids-1", 5, 7), timeout_s=10.0)  # queued behind the samples
    assert reply == []
    assert runner.idle(10.0)
    runner.close()
    assert [e for e, _ in seen] == [f"sample-{i}" for i in range(20)] + ["ids-1"]
    assert {t for _, t in seen} != {threading.get_ident()}
    assert runner.load().handled == 21


def test_full_queue_drops_samples_and_counts_them(samples: list[Sample]) -> None:
    runner = GatedThread(capacity=3)
    runner.start(lambda e: [], lambda: None)
    for i, s in enumerate(samples[:6]):
        runner.post(_sample_event(i, s))
        if i == 0:
            assert runner.entered.wait(10.0)  # the first one is taken: the core is busy with it
    load = runner.load()
    # capacity 3 samples not handled yet: 1 in hand (out of the queue), 2 waiting; the other 3 dropped
    assert load.dropped == 3 and load.queued == 2
    assert runner.pending_since == samples[0].t  # the one in hand is still not handled
    runner.gate.set()
    assert runner.idle(10.0)
    assert runner.pending_since is None
    runner.close()


def _service(model, samples, runner, *, max_lag_s=30.0, loop_lag=None):  # type: ignore[no-untyped-def]
    core = ServiceCore(core_config(Settings()), model=model, history_capacity=1000)
    clock = ManualClock(samples[0].t)
    svc = SoftSensorService(
        core,
        worker=None,
        clock=clock,
        on_event=lambda _m: None,
        runner=runner,
        max_core_lag_s=max_lag_s,
        loop_lag=loop_lag,
    )
    return svc, clock


def test_service_with_core_thread_publishes_every_sample_in_order(loaded_model, samples) -> None:  # type: ignore[no-untyped-def]
    runner = CoreThread(capacity=1000)
    svc, clock = _service(loaded_model, samples, runner)
    published = []
    for s in samples[:12]:
        clock.at_least(s.t)
        svc.on_sample(s)
    assert runner.idle(30.0)
    published.append(svc.view)
    v = svc.view
    assert v.newest is not None and v.newest.t == samples[11].t
    hist = svc.sensor_history(None)
    assert [t for t in hist.t] == [s.t for s in samples[:12]]
    # the view is immutable: frozen dataclass, read-only arrays
    with pytest.raises(dataclasses.FrozenInstanceError):
        v.newest = None  # type: ignore[misc]
    with pytest.raises(ValueError):
        v.newest.temps_c[0] = 0.0
    assert v.live is not None
    with pytest.raises(ValueError):
        v.live.mean[0] = 0.0
    # a later sample replaces the view, never changes the one a reader holds
    svc.on_sample(samples[12])
    assert runner.idle(30.0)
    assert published[0].newest is not None and published[0].newest.t == samples[11].t
    assert svc.view.newest is not None and svc.view.newest.t == samples[12].t
    runner.close()


def test_backlog_past_its_limit_is_served_as_core_behind(loaded_model, samples) -> None:  # type: ignore[no-untyped-def]
    runner = GatedThread(capacity=1000)
    svc, clock = _service(loaded_model, samples, runner, max_lag_s=30.0)
    runner.gate.set()
    for s in samples[:10]:
        clock.at_least(s.t)
        svc.on_sample(s)
    assert runner.idle(30.0)
    runner.gate.clear()
    runner.entered.clear()
    assert DataCode.CORE_BEHIND not in {p.code for p in svc.view.data_problems(clock())}
    for s in samples[10:13]:  # acquired while the core is busy: they wait
        clock.at_least(s.t)
        svc.on_sample(s)
    assert runner.entered.wait(10.0)
    assert svc.view.pending_since == samples[10].t
    clock.advance(31.0)  # the oldest waiting sample is now > 30 s old: nothing served may look fresh
    codes = {p.code for p in svc.view.data_problems(clock())}
    assert DataCode.CORE_BEHIND in codes
    assert any(r.startswith("core_behind") for r in svc.ready().reasons)
    core = next(d for d in svc.health().devices if d.name == "core")
    assert core.status is DeviceStatus.DEGRADED and core.counters["queued"] >= 2
    runner.gate.set()  # the core catches up, in order
    assert runner.idle(30.0)
    assert svc.view.newest is not None and svc.view.newest.t == samples[12].t
    assert svc.view.pending_since is None
    assert DataCode.CORE_BEHIND not in {p.code for p in svc.view.data_problems(clock())}
    assert next(d for d in svc.health().devices if d.name == "core").status is DeviceStatus.OK
    runner.close()


def test_core_behind_verdict_is_typed() -> None:
    from service.serve.policy import data_verdict

    v = data_verdict(
        [DataProblem(DataCode.CORE_BEHIND, "samples wait 40 s")],
        has_sample=True,
        last_good_daq_t=None,
        now=__import__("datetime").datetime.now(__import__("datetime").UTC),
        open_loop_limit_s=600.0,
    )
    assert v is not None and not v.usable
    assert v.status is ChtcStatus.STALE and v.reason is Reason.CORE_BEHIND and v.action


def test_loop_lag_over_limit_degrades_healthz(loaded_model, samples) -> None:  # type: ignore[no-untyped-def]
    now = [0.0]
    lag = LoopLagMonitor(limit_s=0.05, window_s=30.0, monotonic=lambda: now[0])
    svc, _ = _service(loaded_model, samples, None, loop_lag=lag)
    lag.observe(0.002)
    dev = next(d for d in svc.health().devices if d.name == "event_loop")
    assert dev.status is DeviceStatus.OK
    lag.observe(0.2)  # one stall of 200 ms
    dev = next(d for d in svc.health().devices if d.name == "event_loop")
    assert dev.status is DeviceStatus.DEGRADED and dev.message.startswith("loop_lagging")
    now[0] += 31.0  # out of the window: healthy again
    lag.observe(0.001)
    assert next(d for d in svc.health().devices if d.name == "event_loop").status is DeviceStatus.OK
    m = svc.metrics()
    assert m.loop_lag_s is not None and m.loop_lag_s.count == 3


def test_loop_lag_monitor_measures_a_blocked_loop() -> None:
    lag = LoopLagMonitor(limit_s=0.05, period_s=0.01)

    async def main() -> None:
        task = asyncio.ensure_future(lag.run())
        await asyncio.sleep(0.05)
        import time

        time.sleep(0.15)  # the loop blocked: the monitor's next wake-up comes late
        await asyncio.sleep(0.05)
        task.cancel()

    asyncio.run(main())
    assert lag.lag().recent_max_s >= 0.1
    assert lag.lag().over_limit


def test_event_loop_lag_metric_on_metrics_endpoint(loaded_model, samples) -> None:  # type: ignore[no-untyped-def]
    from fastapi.testclient import TestClient

    from api.app import create_app

    lag = LoopLagMonitor(limit_s=0.25)
    svc, clock = _service(loaded_model, samples, CoreThread(capacity=10), loop_lag=lag)
    lag.observe(0.003)
    svc.on_sample(samples[0])
    assert svc.runner.idle(10.0)
    with TestClient(create_app(Settings(), svc, clock=clock)) as client:
        text = client.get("/api/v1/metrics").text
        health = client.get("/healthz").json()
    assert 'chtc_event_loop_lag_seconds_bucket{le="0.005",spindle="spindle1"} 1.0' in text
    assert (
        "chtc_core_wait_seconds_count" in text
        and 'chtc_core_dropped_samples_total{spindle="spindle1"} 0.0' in text
    )
    assert {"core", "event_loop"} <= {d["name"] for d in health["devices"]}
    svc.runner.close()


def test_growth_terms_are_computed_once_per_key(loaded_model, samples) -> None:  # type: ignore[no-untyped-def]
    from service.serve.compensation import GrowthServer

    svc, clock = _service(loaded_model, samples, None)
    for s in samples[:8]:
        clock.at_least(s.t)
        svc.on_sample(s)
    g = GrowthServer(loaded_model)
    view = svc.view
    assert g.refresh(view) is not None and g.computed == 1
    assert g.refresh(view) is not None and g.computed == 1  # cached
    live = view.live
    assert live is not None
    other = dataclasses.replace(view, live=dataclasses.replace(live, h=tuple(1.1 * np.array(live.h))))
    g.refresh(other)
    assert g.computed == 2
    g.refresh(view)  # back to the first H (a speed bin flipping back): from the cache
    assert g.computed == 2
    assert not g.wants_refresh(view) and not g.wants_refresh(other)


def test_inline_is_the_default_and_keeps_the_synchronous_contract(loaded_model, samples) -> None:  # type: ignore[no-untyped-def]
    svc, clock = _service(loaded_model, samples, None)
    clock.at_least(samples[0].t)
    svc.on_sample(samples[0])  # handled before on_sample returns
    assert svc.view.newest is not None and svc.view.newest.t == samples[0].t
    assert not svc.runner.load().threaded
    assert "core" not in {d.name for d in svc.health().devices}
    clock.advance(timedelta(hours=1).total_seconds())
    assert DataCode.CORE_BEHIND not in {p.code for p in svc.view.data_problems(clock())}
