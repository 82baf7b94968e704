"""Issue 41.1: a link that freezes on a batch's COMMIT, and loses the client's FIN, leaves no writer blocked.

Spindle s1 writes through ``tests.db.tcp_proxy.TcpProxy`` (FIN lost, as on a real link), which freezes on the
COMMIT of one of its sample batches: the server keeps that backend with the batch's uncommitted rows (an
orphan); the client's watchdog aborts its side. Spindle s2 writes to the same database directly throughout.
"new_day": the frozen batch is the first of a new UTC day (before the fix it created the day's partition in
its transaction: the orphan held ``samples`` locked against every spindle). "partition": the freeze lands
on the COMMIT of the transaction that makes the partitions ahead of that batch. After the thaw every sample
of s1 is written within 60 s (its service ends its own orphan on reconnecting), none lost, none twice; s2's
writes never wait.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta

import pytest
import sqlalchemy as sa

from service.contracts.records import SampleData
from service.store import migrate
from service.store.engine import create_db_engine, make_session_factory
from service.store.sessions import orphans_ended
from service.store.watchdog import StatementWatchdog
from service.store.writer import DbWriter
from tests.db.conftest import pg_schema_url, spindle_factory
from tests.db.tcp_proxy import TcpProxy, free_port
from tests.db.test_db_spindles import samples

pytestmark = pytest.mark.postgres

DAY = datetime(2026, 3, 1, tzinfo=UTC)
RECOVER_S = 60.0  # the bar: every sample written within this after the thaw
BLOCK_S = 2.0  # s2's flushes: each done within this (its statement timeout), or s2 was blocked


@dataclass
class Spindle:
    writer: DbWriter
    engine: sa.Engine
    watchdog: StatementWatchdog
    sent: list[SampleData]

    def send(self, record: SampleData) -> None:
        assert self.writer.submit(record)
        self.sent.append(record)

    def close(self) -> None:
        self.writer.close(2.0)
        self.watchdog.close()
        self.engine.dispose()


def spindle(url: str, sid: str) -> Spindle:
    engine = create_db_engine(url, connect_timeout_s=2.0, statement_timeout_s=2.0)
    dog = StatementWatchdog(engine, abort_after_s=3.0, poll_s=0.05).start()
    writer = DbWriter(
        make_session_factory(engine, spindle_id=sid),
        watchdog=dog,
        heartbeat_s=1.0,
        stall_s=2.0,
        retry_initial_s=0.2,
        retry_max_s=1.0,
        name=f"w-{sid}",
    ).start()
    return Spindle(writer, engine, dog, [])


@pytest.fixture
def two_spindles(pg_url: str, pg_schema: str) -> Iterator[tuple[TcpProxy, Spindle, Spindle, str]]:
    direct = pg_schema_url(pg_url, pg_schema)
    migrate.upgrade(direct)
    reg = create_db_engine(direct)
    spindle_factory(reg, "s1"), spindle_factory(reg, "s2")
    reg.dispose()
    target = sa.engine.make_url(pg_url)
    port = free_port()
    proxy = TcpProxy(port, (target.host or "127.0.0.1", target.port or 5432), lose_fin=True).start()
    s1 = spindle(pg_schema_url(pg_url, pg_schema, port=port), "s1")
    s2 = spindle(direct, "s2")
    try:
        yield proxy, s1, s2, direct
    finally:
        proxy.thaw()
        s1.close()
        s2.close()
        proxy.stop()


def stored(url: str) -> dict[str, list[datetime]]:
    eng = create_db_engine(url)
    try:
        with eng.connect() as conn:
            rows = conn.execute(sa.text("SELECT spindle_id, t FROM samples ORDER BY spindle_id, t")).all()
    finally:
        eng.dispose()
    out: dict[str, list[datetime]] = {}
    for sid, t in rows:
        out.setdefault(sid, []).append(t)
    return out


@pytest.mark.parametrize(
    "freeze_s", [10.0, pytest.param(60.0, marks=pytest.mark.slow)], ids=["freeze10s", "freeze60s"]
)
@pytest.mark.parametrize("where", ["commit", "new_day", "partition"])
def test_a_freeze_on_commit_that_loses_the_fin_blocks_no_writer(
    two_spindles: tuple[TcpProxy, Spindle, Spindle, str], where: str, freeze_s: float
) -> None:
    proxy, s1, s2, direct = two_spindles
    t0 = DAY + timedelta(hours=8)
    for s, base in ((s1, 30.0), (s2, 40.0)):
        for smp in samples(20, base=base, start=t0):
            s.send(smp)
        assert s.writer.flush(10.0)

    # the next batch of s1 freezes at its COMMIT; s1 and s2 keep storing a sample every 0.1 s throughout
    start = t0 + timedelta(minutes=10) if where == "commit" else DAY + timedelta(days=1)
    stream1 = iter(samples(10_000, base=31.0, start=start))
    stream2 = iter(samples(10_000, base=41.0, start=start))
    proxy.freeze_on(b"COMMIT", after=b"ATTACH PARTITION" if where == "partition" else b"INSERT INTO samples")
    s1.send(next(stream1))
    assert proxy.frozen.wait(10.0), f"the link never froze on a COMMIT ({where})"
    frozen_at = time.monotonic()
    s2_waits: list[float] = []
    next_check = frozen_at
    while time.monotonic() - frozen_at < freeze_s:
        s1.send(next(stream1))
        s2.send(next(stream2))
        if time.monotonic() >= next_check:  # s2's backlog written within its statement timeout, every 0.5 s
            t = time.monotonic()
            s2.writer.flush(BLOCK_S + 1.0)
            s2_waits.append(time.monotonic() - t)
            next_check = time.monotonic() + 0.5
        time.sleep(0.1)
    assert proxy.abandoned >= 1, "no connection was given up during the freeze: no orphan to test"
    assert s1.writer.status().pending > 0
    proxy.thaw()
    thawed = time.monotonic()

    while s1.writer.status().pending and time.monotonic() - thawed < RECOVER_S + 30.0:
        time.sleep(0.05)
    recovered_s = time.monotonic() - thawed
    print(
        f"{where}, freeze {freeze_s:.0f} s: s1 backlog written {recovered_s:.1f} s after the thaw; "
        f"s2's longest flush {max(s2_waits):.2f} s; orphans ended {orphans_ended(s1.engine)}; "
        f"connections abandoned {proxy.abandoned}"
    )
    assert recovered_s <= RECOVER_S, f"s1's backlog not written within {RECOVER_S} s of the thaw"
    assert s2.writer.flush(5.0)
    assert max(s2_waits) < BLOCK_S, s2_waits  # s2 never waited on s1's orphan
    assert s2.writer.status().errors == 0, s2.writer.status()

    rows = stored(direct)
    for sid, s in (("s1", s1), ("s2", s2)):
        sent = sorted(r.t for r in s.sent)
        assert rows[sid] == sent, (
            f"{sid}: {len(rows[sid])} stored of {len(sent)} sent"
        )  # none lost, none twice
