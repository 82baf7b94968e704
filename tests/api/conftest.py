"""Fixtures for the API tests: the real service (``simulator.served``: the core and shell fed a
virtual-plant run, real SQLite in the test's tmp dir), its hand-moved clock, the app, a live uvicorn server.

``served`` is function-scoped (about 0.5 s: the plant run is computed once per process, the model comes from
the ROM cache): most tests change the service's state (its clock, samples, jobs).
"""

from __future__ import annotations

import contextlib
import socket
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import httpx
import pytest
import uvicorn
from fastapi import FastAPI
from fastapi.testclient import TestClient

from api.app import create_app
from drivers.can_sensor import CanSpindleSensor
from drivers.errors import DeviceError
from drivers.modbus_daq import ModbusDaq
from service.settings import Settings
from service.shell.service import SoftSensorService
from simulator.duty import duty_profile
from simulator.served import DEMO_FED, ManualClock, Plan, Served, served_service
from tests.modes import PER_CONDITION

__all__ = [
    "DEMO_WINDOWS",
    "MAP_FED",
    "MAP_MODE",
    "MAP_PLAN",
    "WRITE_TOKEN",
    "LiveServer",
    "ManualClock",
    "free_port",
    "served_map_mode",
    "sqlite_url",
]

WRITE_TOKEN = "write-token-for-tests"
# A 10-min window from a cold start leaves every 95 % CI wide (half-widths of log H up to about 19 on the
# demo plan): the default threshold (0.5) calls no H identified. This one makes the real rule call the newest
# identification's H all identified, for the tests of what follows from that (usable_for_compensation).
LENIENT_CI = 25.0
# With the filtered live state (issue 16), a cold start at 3000 rpm with no rest and no offset baseline
# leaves H1/H4 degenerate whatever the threshold: the unknown offsets' 1σ (0.173 °C) widens the filter's
# measurement noise and the fit's CIs (docs/design/estimator.md). Tests that need every H identified (the
# usable flag, the dashboard's identified state) therefore run with known offsets: calibration off, no offset
# term. The demo plan (11 min per condition) and what these tests expect of it were built on 10-min first
# windows; since issue 16 the service's first window is 7 min (the first H within 13 min of a restart), which
# on this cold start without rest leaves H1/H5 on a bound. The API tests run the demo with its 10-min windows.
# They run it in per-condition mode (the paper's protocol), whatever the default: their expectations (ids 1
# and 2, one identification per condition, the `identifying` status while a job runs or after a condition
# change, the counts) are that protocol's; the speed map's API is tested on MAP_MODE below
# (test_api_chtc_map.py, test_api_dashboard.py's map cases, test_api_compensation.py's map case).
DEMO_WINDOWS = {"schedule_min": (10.0, 20.0, 40.0, 60.0), "min_window_s": 600.0}  # with PER_CONDITION
LENIENT_IDENTIFICATION = {"ci_rel_threshold": LENIENT_CI, "offset_calibration": False, **DEMO_WINDOWS}


# Speed-map mode (issue 17, docs/design/hmap.md) on a seeded duty cycle (simulator.duty: 5 min at rest, then
# the speed changes every 1-6 min): the first map fit comes after experimental.map_min_window_min (10 min) of
# data, re-fits follow the changes. The first MAP_FED samples (26.7 min) give several fits.
MAP_MODE = Settings(identification={"mode": "speed_map"})
MAP_PLAN = Plan(profile=tuple(duty_profile(7, duration_s=1800.0)))
MAP_FED = 160


def served_map_mode(tmp: Path, *, feed_samples: int = MAP_FED) -> Served:
    """The real service in speed-map mode fed the first ``feed_samples`` samples of ``MAP_PLAN``."""
    return served_service(
        database_url=sqlite_url(tmp, "map.db"), plan=MAP_PLAN, settings=MAP_MODE, feed_samples=feed_samples
    )


def sqlite_url(tmp: Path, name: str = "chtc.db") -> str:
    return f"sqlite:///{tmp / name}"


@pytest.fixture
def served(tmp_path: Path) -> Iterator[Served]:
    """The demo plan's first 22 min (3000 rpm, then 4000 rpm, 11 min each) fed through the real service: two
    identifications (ids 1 and 2, one per condition), condition 2 current, fresh, no H identified (default CI
    threshold); ``served.feed_next()`` feeds up to 30 more samples at 4000 rpm."""
    demo = Settings(identification={**DEMO_WINDOWS, **PER_CONDITION})
    with served_service(database_url=sqlite_url(tmp_path), settings=demo, feed_samples=DEMO_FED) as s:
        yield s


@pytest.fixture(scope="package")
def served_ro(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Served]:
    """The same service, shared by the tests that only read it and never move its clock (request
    validation, the OpenAPI document): built once for tests/api and closed after its last test (session
    scope kept its database writer probing through every later package: test_logctx saw its SQL)."""
    url = sqlite_url(tmp_path_factory.mktemp("served-ro"))
    demo = Settings(identification={**DEMO_WINDOWS, **PER_CONDITION})
    with served_service(database_url=url, settings=demo, feed_samples=DEMO_FED) as s:
        yield s


@pytest.fixture
def ro_service(served_ro: Served) -> SoftSensorService:
    return served_ro.service


@pytest.fixture
def ro_clock(served_ro: Served) -> ManualClock:
    return served_ro.clock


@pytest.fixture
def ro_app(settings: Settings, served_ro: Served) -> FastAPI:
    return create_app(settings, served_ro.service, clock=served_ro.clock)


@pytest.fixture
def ro_client(ro_app: FastAPI) -> Iterator[TestClient]:
    with TestClient(ro_app) as c:
        yield c


@pytest.fixture
def clock(served: Served) -> ManualClock:
    return served.clock


@pytest.fixture
def service(served: Served) -> SoftSensorService:
    return served.service


@pytest.fixture
def settings() -> Settings:
    return Settings(api={"token": WRITE_TOKEN})


@pytest.fixture
def app(settings: Settings, service: SoftSensorService, clock: ManualClock) -> FastAPI:
    return create_app(settings, service, clock=clock)


@pytest.fixture
def client(app: FastAPI) -> Iterator[TestClient]:
    with TestClient(app) as c:
        yield c


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class LiveServer:
    """uvicorn in a thread on a free loopback port; stopped through ``should_exit``."""

    def __init__(self, app: FastAPI) -> None:
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        config = uvicorn.Config(app, host="127.0.0.1", port=self.port, log_level="warning", lifespan="off")
        self.server = uvicorn.Server(config)
        self.thread = threading.Thread(target=self.server.run, daemon=True)

    def __enter__(self) -> LiveServer:
        self.thread.start()
        deadline = time.monotonic() + 10.0
        while time.monotonic() < deadline:
            try:
                if httpx.get(self.url + "/api/v1/healthz", timeout=0.5).status_code == 200:
                    return self
            except httpx.TransportError:
                time.sleep(0.02)
        raise RuntimeError(f"uvicorn did not start on {self.url}")

    def __exit__(self, *exc: object) -> None:
        self.server.should_exit = True
        self.thread.join(timeout=10.0)


@pytest.fixture
def served_db_down(tmp_path: Path) -> Iterator[Served]:
    """The same service on a database that cannot be opened (the SQLite "file" is a directory): it starts
    without restored state, holds its records and serves what it remembers."""
    (tmp_path / "a-directory").mkdir()
    url = sqlite_url(tmp_path, "a-directory")
    demo = Settings(
        identification={**DEMO_WINDOWS, **PER_CONDITION}
    )  # per condition: the two identifications it holds
    with served_service(database_url=url, settings=demo, feed_samples=DEMO_FED) as s:
        yield s


def served_with_dead_devices(
    tmp_path: Path, *, devices: tuple[str, ...] = ("modbus", "can"), settings: Settings | None = None
) -> Served:
    """The demo service with real drivers that cannot reach their devices, each read twice: a Modbus DAQ on a
    loopback port nobody listens on (refused) and a CAN sensor on a virtual channel nobody sends on."""
    make: dict[str, Callable[[], ModbusDaq | CanSpindleSensor]] = {
        "modbus": lambda: ModbusDaq("127.0.0.1", free_port(), timeout_s=0.5),
        "can": lambda: CanSpindleSensor(
            interface="virtual", channel=f"chtc-silent-{tmp_path.name}", stale_after_s=0.2
        ),
    }
    sources = {name: make[name]() for name in devices}

    async def read_twice() -> None:
        for src in sources.values():
            for _ in range(2):
                with contextlib.suppress(DeviceError):
                    await src.read()

    s = served_service(
        database_url=sqlite_url(tmp_path), settings=settings, feed_samples=DEMO_FED, sources=sources
    )
    s.call(read_twice)
    return s


@pytest.fixture
def served_devices_down(tmp_path: Path) -> Iterator[Served]:
    with served_with_dead_devices(tmp_path) as s:
        yield s
