"""The outlet seam (issue 28 item 1, ``service.serve.outlet``): subscribed outlets get the newest view's
reader on the event loop, coalesced and rate-limited; the reader answers what the service (REST) answers; the
runtime picks the enabled outlets; ``service`` never imports ``api`` (also ``tests/test_layers.py``)."""

from __future__ import annotations

import ast
import asyncio
import threading
from pathlib import Path

import pytest

from drivers.ringbuffer import Sample
from model.plant import Segment
from service.core.machine import ServiceCore
from service.host.runtime import core_config, enabled_outlets
from service.serve.errors import OutletError
from service.serve.outlet import OUTLETS, load_factory
from service.serve.reader import ViewReader
from service.settings import Settings
from service.shell.service import SoftSensorService
from simulator.served import ManualClock

from .conftest import plant_run, samples_of

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def samples() -> list[Sample]:
    return samples_of(plant_run([Segment(600.0, 0.0, 0.0, 22.0)], seed=5))


class Recorder:
    name = "recorder"

    def __init__(self) -> None:
        self.readers: list[ViewReader] = []
        self.threads: set[int] = set()
        self.got = asyncio.Event()

    async def start(self) -> None: ...

    def on_view(self, reader: ViewReader) -> None:
        self.readers.append(reader)
        self.threads.add(threading.get_ident())
        self.got.set()

    async def close(self) -> None: ...


class Broken(Recorder):
    name = "broken"

    def on_view(self, reader: ViewReader) -> None:
        raise RuntimeError("outlet bug")


def _service(model, samples, interval_s):  # type: ignore[no-untyped-def]
    core = ServiceCore(core_config(Settings()), model=model, history_capacity=1000)
    clock = ManualClock(samples[0].t)
    svc = SoftSensorService(
        core, worker=None, clock=clock, on_event=lambda _m: None, outlet_interval_s=interval_s
    )
    return svc, clock


async def _wait(cond, timeout_s: float = 10.0) -> None:  # type: ignore[no-untyped-def]
    deadline = asyncio.get_running_loop().time() + timeout_s
    while not cond():
        assert asyncio.get_running_loop().time() < deadline, "timed out"
        await asyncio.sleep(0.01)


def test_outlets_get_the_newest_view_coalesced_on_the_loop(loaded_model, samples) -> None:  # type: ignore[no-untyped-def]
    async def run() -> None:
        svc, clock = _service(loaded_model, samples, 0.2)
        rec, broken = Recorder(), Broken()
        svc.subscribe(broken)  # its exception is logged; the recorder still gets every delivery
        svc.subscribe(rec)
        await svc.start()
        await _wait(lambda: len(rec.readers) == 1)  # the current view, at start
        for s in samples[:30]:  # 30 publishes within far less than 0.2 s: one delivery after the first
            clock.at_least(s.t)
            svc.on_sample(s)
        await _wait(
            lambda: rec.readers[-1].view.newest is not None and rec.readers[-1].view.newest.t == samples[29].t
        )
        await asyncio.sleep(0.3)  # no more publishes: no more deliveries
        assert 2 <= len(rec.readers) <= 3, len(rec.readers)
        assert rec.threads == {threading.get_ident()}  # on the loop's thread
        last = rec.readers[-1]
        assert last.view is svc.view
        # the reader answers what the service (REST) answers, same verdicts
        assert last.sensors() == svc.sensors()
        assert last.condition() == svc.condition()
        assert last.ready() == svc.ready()
        assert [d.name for d in last.health().devices] == [d.name for d in svc.health().devices]
        svc.unsubscribe(rec)
        n = len(rec.readers)
        clock.at_least(samples[30].t)
        svc.on_sample(samples[30])
        await asyncio.sleep(0.4)
        assert len(rec.readers) == n
        await svc.close()

    asyncio.run(run())


def test_runtime_starts_rest_and_the_enabled_outlets() -> None:
    s = Settings()
    assert enabled_outlets(s, api=True) == ["rest"]
    assert enabled_outlets(s, api=False) == []
    assert set(OUTLETS) >= {"rest", "opcua"}
    with pytest.raises(OutletError, match="unknown outlet"):
        load_factory("carrier-pigeon")
    with pytest.raises(OutletError, match="cannot load"):
        load_factory("x", {"x": "no.such.module:factory"})
    assert load_factory("rest").__module__ == "api.outlet"


def test_nothing_under_service_imports_api() -> None:
    """The REST outlet is found by name; ``service`` imports ``api`` nowhere (any import, anywhere)."""
    found = []
    for path in sorted((ROOT / "service").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            names = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and not node.level:
                names = [node.module or ""]
            found += [f"{path.relative_to(ROOT)}: {n}" for n in names if n == "api" or n.startswith("api.")]
    assert found == []
    # the checker sees such an import where there is one
    assert any(
        isinstance(n, ast.ImportFrom) and n.module == "api.app"
        for n in ast.walk(ast.parse((ROOT / "api" / "outlet.py").read_text()))
    )
