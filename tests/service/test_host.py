"""Several spindles in one process (issue 29, item 5): real drivers against simulated devices, one shared
identification pool, one shared database, one REST server at a speed-up.

Two spindles of one geometry run beside a third whose register map file does not exist; the third is
reported and the two serve under ``/api/v1/spindles/{id}/…`` with one model and one pool. Then spindle a's
DAQ hangs: a goes stale, b stays ``fresh`` throughout. Slow: about a minute."""

from __future__ import annotations

import asyncio
import logging
import time
from pathlib import Path

import httpx
import pytest

from drivers.sim.faults import FaultKind
from model.plant import Segment
from service.host.fleet import Host
from service.host.runtime import ScaledClock, free_port
from service.logctx import SpindleFilter
from service.settings import Settings
from simulator.simrig import SimAddress, make_drivers, plant_rig
from tests.db.conftest import pg_schema, pg_schema_url

from .conftest import plant_run

__all__ = ["pg_schema"]  # a fixture of tests/db, used here

pytestmark = pytest.mark.slow
SPEEDUP = 40.0


async def _until(pred, timeout_s: float, every_s: float = 0.1) -> bool:  # type: ignore[no-untyped-def]
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if await pred():
            return True
        await asyncio.sleep(every_s)
    return False


def host_settings(db_url: str, addresses: dict[str, SimAddress], bad_map: Path) -> Settings:
    entries = [
        {"id": sid, "modbus": {"port": a.port}, "can": {"channel": a.channel}} for sid, a in addresses.items()
    ]
    # first in the file: a spindle that fails before its start must not leave the schema unmigrated
    entries.insert(
        0, {"id": "c", "modbus": {"port": free_port(), "register_map": str(bad_map)}, "can": {"channel": "c"}}
    )
    return Settings(
        spindles=entries,
        api={"port": free_port()},
        database={"url": db_url},
        engine={"identification_workers": 1},
    )


async def scenario(db_url: str, bad_map: Path) -> dict[str, object]:
    addresses = {sid: SimAddress.free(speedup=SPEEDUP) for sid in ("a", "b")}
    settings = host_settings(db_url, addresses, bad_map)
    clock = ScaledClock(SPEEDUP)
    by_port = {a.port: a for a in addresses.values()}

    def devices(s: Settings):  # type: ignore[no-untyped-def]
        if (
            s.modbus.register_map is not None
        ):  # the third spindle: its map is loaded (and fails) as in chtc run
            from service.commands.run import make_device_drivers

            return make_device_drivers(s, clock=clock)
        return make_drivers(s, by_port[s.modbus.port], clock=clock)

    events: list[str] = []
    host = Host(settings=settings, clock=clock, devices=devices, on_event=events.append, simulated_time=True)
    run = plant_run([Segment(7200.0, 3000.0, 5.0, 22.0)], seed=11)
    rigs = []
    out: dict[str, object] = {"events": events, "addresses": addresses}
    try:
        await host.start(api=True)
        await host.wait_api()
        rigs = [await plant_rig(run, address=a) for a in addresses.values()]
        base = host.url.rstrip("/")
        async with httpx.AsyncClient(base_url=base, timeout=5.0) as client:

            async def status(sid: str) -> str | None:
                r = await client.get(f"/api/v1/spindles/{sid}/chtc")
                return r.json().get("status") if r.status_code == 200 else None

            async def both_fresh() -> bool:
                return await status("a") == "fresh" and await status("b") == "fresh"

            out["both_fresh"] = await _until(both_fresh, 150.0)
            out["list"] = (await client.get("/api/v1/spindles")).json()
            out["old_path"] = await client.get("/api/v1/chtc")
            out["unknown"] = await client.get("/api/v1/spindles/zz/chtc")
            out["metrics"] = (await client.get("/metrics")).text
            out["sensors_a"] = (await client.get("/api/v1/spindles/a/sensors")).json()
            out["chtc_b"] = await client.get("/api/v1/spindles/b/chtc")
            out["healthz"] = {
                sid: (await client.get(f"/api/v1/spindles/{sid}/healthz")).json() for sid in "ab"
            }
            out["loop_lags"] = [
                h.runtime.service.loop_lag
                for h in host.spindles.values()
                if h.runtime is not None and h.runtime.service is not None
            ]
            out["host_loop_lag"] = host.loop_lag
            out["readyz"] = await client.get("/readyz")
            out["models"] = len(host.models)
            assert host.pool is not None
            out["pool_pids"] = host.pool.pids()
            out["pool_jobs"] = host.pool.jobs_run

            fault = rigs[0].daq_server.faults.inject(FaultKind.HANG)
            b_seen: list[str | None] = []

            async def a_stale_b_watched() -> bool:
                b_seen.append(await status("b"))
                return await status("a") == "stale"

            out["a_stale"] = await _until(a_stale_b_watched, 60.0)
            for _ in range(10):  # and b stays fresh while a is down
                b_seen.append(await status("b"))
                await asyncio.sleep(0.2)
            out["b_during"] = b_seen
            rigs[0].daq_server.faults.clear(fault)
    finally:
        await host.stop()
        for rig in rigs:
            await rig.stop()
    out["stored"] = stored_samples(db_url)
    return out


def stored_samples(db_url: str) -> dict[str, int]:
    """Sample rows per spindle in the shared database (every spindle wrote its own, keyed by its id)."""
    import sqlalchemy as sa

    engine = sa.create_engine(db_url)
    try:
        with engine.connect() as conn:
            rows = conn.execute(sa.text("SELECT spindle_id, count(*) FROM samples GROUP BY spindle_id")).all()
    finally:
        engine.dispose()
    return {str(sid): int(n) for sid, n in rows}


@pytest.fixture
def pg_schema_db(pg_url: str, pg_schema: str) -> str:
    """A fresh PostgreSQL schema (the fleet's database), dropped after the test."""
    return pg_schema_url(pg_url, pg_schema)


@pytest.mark.postgres
def test_two_spindles_share_one_process_and_a_daq_down_is_only_its_own(
    pg_schema_db: str, tmp_path: Path
) -> None:
    records = _Records()
    root = logging.getLogger()
    root.addHandler(records)
    try:
        out = asyncio.run(scenario(pg_schema_db, tmp_path / "missing-map.toml"))
    finally:
        root.removeHandler(records)
    assert out["both_fresh"], out["events"]
    rows = {r["id"]: r for r in out["list"]["spindles"]}  # type: ignore[index]
    assert set(rows) == {"a", "b", "c"}
    assert rows["a"]["running"] and rows["b"]["running"] and not rows["c"]["running"]
    assert "missing-map.toml" in rows["c"]["error"]
    old = out["old_path"]
    assert old.status_code == 404 and "/api/v1/spindles/{id}/" in old.json()["error"]["message"]  # type: ignore[attr-defined]
    assert out["unknown"].status_code == 404  # type: ignore[attr-defined]
    metrics = str(out["metrics"])
    assert 'spindle="a"' in metrics and 'spindle="b"' in metrics
    assert metrics.count("# TYPE chtc_growth_um ") == 1  # one family, both spindles' samples
    assert out["readyz"].status_code == 200  # type: ignore[attr-defined]
    assert out["models"] == 1  # one geometry, one reduced model
    assert len(out["pool_pids"]) == 1 and int(out["pool_jobs"]) >= 2  # type: ignore[arg-type]
    assert len(out["sensors_a"]["channels"]) == 32  # type: ignore[index]
    # one loop, one lag monitor (the host's), read by every spindle's /healthz
    lags = out["loop_lags"]
    assert len(lags) == 2 and all(lag is out["host_loop_lag"] for lag in lags), lags  # type: ignore[arg-type]
    for sid, health in out["healthz"].items():  # type: ignore[attr-defined]
        (loop,) = [d for d in health["devices"] if d["name"] == "event_loop"]
        assert loop["status"] in ("ok", "degraded") and "max lag" in loop["message"], (sid, loop)
        assert loop["counters"]["observations"] > 0, (sid, loop)  # measured: the host runs it
    assert out["a_stale"]
    assert out["b_during"] and all(s == "fresh" for s in out["b_during"]), out["b_during"]  # type: ignore[union-attr]
    rows_per_spindle = out["stored"]
    assert set(rows_per_spindle) == {"a", "b"} and min(rows_per_spindle.values()) > 0, rows_per_spindle  # type: ignore[union-attr]
    # each spindle's answers and log lines name it (service.logctx, api/spindlehdr.py)
    chtc_b = out["chtc_b"]
    assert chtc_b.json()["spindle_id"] == "b" and chtc_b.headers["Chtc-Spindle-Id"] == "b"  # type: ignore[attr-defined]
    ports = {str(a.port): sid for sid, a in out["addresses"].items()}  # type: ignore[attr-defined]
    device_lines = [
        (sid, r.spindle)  # type: ignore[attr-defined]
        for r in records.records
        if r.name.startswith("drivers")
        for port, sid in ports.items()
        if f":{port}" in r.getMessage()
    ]
    assert ("a", "a") in device_lines, device_lines  # a's hang was logged, as spindle a
    assert all(sid == spindle for sid, spindle in device_lines), device_lines


class _Records(logging.Handler):
    def __init__(self) -> None:
        super().__init__(logging.INFO)
        self.records: list[logging.LogRecord] = []
        self.addFilter(SpindleFilter())

    def emit(self, record: logging.LogRecord) -> None:
        self.records.append(record)
