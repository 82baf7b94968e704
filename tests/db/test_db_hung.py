"""Issue 13.2: a hung PostgreSQL (a frozen link: no RST, no FIN) is visible within 10 s and loses nothing.

A real PostgreSQL behind ``tests.db.tcp_proxy.TcpProxy``, which ``freeze()``s: connections stay open, nothing
is forwarded, and the close of a connection the service gives up on meanwhile is lost, as on a real link: its
server session stays behind (issue 41.1: with the close delivered at the thaw, the orphan was hidden, and this
test still failed 2 of 5 runs under load when the freeze landed on a batch's COMMIT). The service is the real
one (``simulator.served``: ``open_persistence``, the core, the shell and the API, as in production, only
with short database timeouts), fed virtual-plant samples; each sample it takes is stored
(``database.sample_store_period_s`` = the 10-s sample period).
"""

from __future__ import annotations

import os
import time
from collections.abc import Iterator

import pytest
import sqlalchemy as sa
from fastapi.testclient import TestClient

from model.plant import Segment
from service.settings import Settings
from service.store import repository as repo
from service.store.engine import create_db_engine, make_session_factory
from service.store.models import SampleRow
from simulator.served import Plan, Served, served_service
from tests.db.conftest import pg_schema_url
from tests.db.tcp_proxy import TcpProxy, free_port

pytestmark = [pytest.mark.postgres, pytest.mark.slow]  # waits out a frozen database's limit (~15 s at load 8)

FREEZE_S = float(os.environ.get("CHTC_TEST_FREEZE_S", "15"))  # the outage was 60 s: set it to 60
# samples enough for 20 before the freeze and one per 50 ms through a 60-s freeze
PLAN = Plan(profile=(Segment(12_600.0, 4000.0, 10.0, 22.0),))


def db_health(client: TestClient) -> tuple[str, str, str]:
    """(overall status, db status, db message) from GET /api/v1/healthz."""
    body = client.get("/api/v1/healthz").json()
    (dev,) = [d for d in body["devices"] if d["name"] == "db"]
    return body["status"], dev["status"], dev["message"]


@pytest.fixture
def proxied(pg_url: str, pg_schema: str) -> Iterator[tuple[TcpProxy, Served, str]]:
    target = sa.engine.make_url(pg_url)
    port = free_port()
    proxy = TcpProxy(port, (target.host or "127.0.0.1", target.port or 5432)).start()
    db = Settings().database.model_copy(
        update={
            "connect_timeout_s": 2.0,
            "statement_timeout_s": 2.0,
            "heartbeat_s": 1.0,
            "stall_s": 2.0,
            "read_timeout_s": 1.0,
            "read_threads": 2,
            "retry_initial_s": 0.2,
            "retry_max_s": 1.0,
        }
    )
    url = pg_schema_url(pg_url, pg_schema, port=port)
    served = served_service(database_url=url, plan=PLAN, settings=Settings(database=db), feed_samples=0)
    assert served.persistence.restored_from_db
    try:
        yield proxy, served, pg_schema_url(pg_url, pg_schema)
    finally:
        proxy.thaw()
        served.close()
        proxy.stop()


@pytest.mark.parametrize("writing", [True, False], ids=["writing", "idle"])
def test_frozen_database_is_degraded_within_10_s_and_nothing_is_lost(
    proxied: tuple[TcpProxy, Served, str], writing: bool
) -> None:
    """``writing``: samples keep coming during the freeze; idle: only the writer's heartbeat can notice it."""
    from api.app import create_app

    proxy, served, direct = proxied
    client = TestClient(create_app(Settings(), served.service, clock=served.clock))
    sink = served.persistence.sink
    served.feed_next(20)
    assert sink.writer.flush(15.0)
    assert db_health(client)[:2] == ("ok", "ok")

    proxy.freeze()
    frozen_at = time.monotonic()
    seen: list[tuple[float, str, str, str]] = []
    read_statuses: list[tuple[int, float]] = []
    while time.monotonic() - frozen_at < FREEZE_S:
        if writing:
            served.feed_next(1)  # the service keeps taking samples and storing them (one per 50 ms here)
        overall, status, message = db_health(client)
        if not seen or seen[-1][2] != status:
            seen.append((time.monotonic() - frozen_at, overall, status, message))
        if len(read_statuses) < 3 and time.monotonic() - frozen_at > 1.0:
            t = time.monotonic()
            r = client.get("/api/v1/identifications/424242")  # not in memory: a database read
            read_statuses.append((r.status_code, time.monotonic() - t))
            assert r.json()["error"]["code"] == "not_ready" and "Retry-After" in r.headers
        time.sleep(0.05)
    proxy.thaw()
    print(f"freeze {FREEZE_S:.0f} s: health transitions {seen}; reads {read_statuses}; {served.fed} samples")

    changed = [s for s in seen if s[2] != "ok"]
    assert changed, f"db health never left ok during a {FREEZE_S:.0f} s freeze: {seen}"
    first_t, overall, first_status, first_msg = changed[0]
    assert first_t <= 10.0 and (overall, first_status) == ("degraded", "degraded"), seen
    assert "not answering" in first_msg
    # reads answer 503 within the read timeout (+ slack), never hang with the database
    assert read_statuses and all(code == 503 and dt < 3.0 for code, dt in read_statuses), read_statuses

    deadline = time.monotonic() + 30.0
    while sink.status().pending and time.monotonic() < deadline:
        time.sleep(0.05)
    assert sink.status().pending == 0
    assert db_health(client)[:2] == ("ok", "ok")
    eng = create_db_engine(direct)
    with repo.session_scope(make_session_factory(eng)) as s:
        stored = [r.t for r in repo.list_samples(s, limit=10_000)]
        assert repo.count_rows(s, SampleRow) == served.fed  # every row once: none lost, none doubled
    eng.dispose()
    assert stored == [smp.t for smp in served.samples[: served.fed]]
