"""End to end: virtual plant -> simulated Modbus DAQ + CAN node -> the service (real drivers, detector,
scheduler, worker process, SQLite) -> the API over HTTP (uvicorn), at a high speed-up.

The spindle idles cold for 5 plant minutes (the service is up before the machine runs), then three conditions
(3000, 4000, 5000 rpm, 45 plant minutes each). The service must detect each change,
identify each condition (the later ones warm-started from an earlier condition), store everything, and
GET /api/v1/chtc must return H close to the plant's truth (see the note at the final assertions).
"""

from __future__ import annotations

import asyncio
import time

import httpx
import numpy as np
import pytest

from model.geometry import load_spindle
from model.plant import Segment, VirtualPlant, h_true
from service.host.runtime import Runtime, ScaledClock, free_port
from service.settings import Settings
from simulator.simrig import SimAddress, make_drivers, plant_rig
from tests.modes import per_condition

# 150 plant s per wall s: the 8400 plant s take 56 s wall (84 s at 100x). Measured alone at 100x and
# 150x (2026-11-27, load ~2-3): the same assertions with the same margins (median |error| 5.2 % at 100x,
# 5.1 % and 6.7 % at 150x; H6 within 0.3 %); the identification jobs and the detector run in plant time.
SPEEDUP = 150.0
SEGMENTS = [
    Segment(300.0, 0.0, 0.0, 23.2),
    Segment(2700.0, 3000.0, 5.0, 23.2),
    Segment(2700.0, 4000.0, 6.0, 21.8),
    Segment(2700.0, 5000.0, 8.0, 22.0),
]


def e2e_settings(db_url: str) -> Settings:
    # per-condition mode: the test asserts its protocol (each condition identified, the later ones
    # warm-started from an earlier condition, the final answer from the 5000-rpm condition's >= 35-min window)
    s = per_condition()
    return s.model_copy(
        update={
            "api": s.api.model_copy(update={"port": free_port()}),
            "database": s.database.model_copy(update={"url": db_url}),
        }
    )


async def scenario(db_url: str, run) -> dict:
    settings = e2e_settings(db_url)
    clock = ScaledClock(SPEEDUP)
    events: list[str] = []
    runtime = Runtime(settings=settings, clock=clock, on_event=events.append)
    await asyncio.to_thread(runtime.load)
    address = SimAddress.free(speedup=SPEEDUP)
    daq, can_sensor = make_drivers(settings, address, clock=clock)
    polls: list[dict] = []
    rig = None
    try:
        await runtime.start(daq=daq, can=can_sensor, api=True)
        await runtime.wait_api()
        rig = await plant_rig(run, address=address)
        deadline = time.monotonic() + sum(seg.duration_s for seg in SEGMENTS) / SPEEDUP + 60.0
        async with httpx.AsyncClient(base_url=runtime.url.rstrip("/"), timeout=10.0) as client:
            while time.monotonic() < deadline:
                r = await client.get("/api/v1/chtc")
                if r.status_code == 200:
                    polls.append(r.json())
                    body = polls[-1]
                    if body["condition"]["speed_rpm"] > 4500 and _window_min(runtime, body) >= 35:
                        break
                else:
                    assert r.status_code == 503 and r.json()  # no identification yet: typed error body
                await asyncio.sleep(0.25)
        rows = _stored(runtime)
        ring = runtime.ring.window(0.0, 1e12)
        t_plant0 = time.time() - rig.plant_time_s()
    finally:
        await runtime.stop()
        if rig is not None:
            await rig.stop()
    return {"polls": polls, "rows": rows, "events": events, "ring": ring, "t_plant0": t_plant0}


def _window_min(runtime: Runtime, body: dict) -> float:
    rec = runtime.service.get_identification(body["identification_id"])
    return (rec.window_to - rec.window_from).total_seconds() / 60.0


def _stored(runtime: Runtime) -> list[dict]:
    from service.store.repository import list_identifications, session_scope

    runtime.persistence.sink.writer.flush(10.0)
    with session_scope(runtime.persistence.session_factory) as session:
        page = list_identifications(session, limit=200)
        return [
            {
                "outcome": r.outcome,
                "condition_speed": r.condition.speed_rpm,
                "warm": r.warm_start_source,
                "h": r.h,
                "window_min": (r.window_end - r.window_start).total_seconds() / 60.0,
            }
            for r in page.items
        ]


@pytest.mark.slow
def test_three_conditions_detected_identified_and_served(tmp_path):
    run = VirtualPlant(load_spindle(), seed=3).run(SEGMENTS, dt_s=10.0)
    out = asyncio.run(scenario(f"sqlite:///{tmp_path / 'e2e.db'}", run))
    polls, rows = out["polls"], out["rows"]
    # every condition was detected (and served by the API while it was current)
    speeds = sorted({round(p["condition"]["speed_rpm"], -2) for p in polls})
    assert speeds == [3000, 4000, 5000], out["events"][-20:]
    # every condition was identified; conditions 2 and 3 were warm-started from an earlier condition
    ok = [r for r in rows if r["outcome"] == "ok"]
    assert {round(r["condition_speed"], -2) for r in ok} == {3000, 4000, 5000}
    first_of = {}
    for r in sorted(ok, key=lambda r: r["window_min"]):
        first_of.setdefault(round(r["condition_speed"], -2), r)
    assert first_of[4000]["warm"].startswith("condition") and first_of[5000]["warm"].startswith("condition")
    # the final answer: condition 3 from a >= 35 min window that explains the data (noise 0.15 °C)
    body = polls[-1]
    assert body["condition"]["speed_rpm"] == pytest.approx(5000.0, abs=50)
    assert body["status"] in ("fresh", "identifying")
    assert body["fit"] > 0.95 and body["rmse_c"] < 0.3
    truth = h_true(5000.0, 22.0)
    h = np.array([z["h_w_m2k"] for z in body["zones"]])
    lo = np.array([z["ci95_lo_w_m2k"] for z in body["zones"]])
    hi = np.array([z["ci95_hi_w_m2k"] for z in body["zones"]])
    identified = np.array([z["identified"] for z in body["zones"]])
    # Every H flagged identified covers the truth (no silent bias). The 5-min idle at the start gives the
    # sensor-offset baseline (service.acquire.calibration), whose own error (σ/√30 ≈ 0.027 °C per channel) is
    # carried in the CIs, so a run may flag none.
    covered = (lo <= truth) & (truth <= hi)
    err = np.abs(h - truth) / truth
    detail = {"h": h, "lo": lo, "hi": hi, "truth": truth, "identified": identified}
    assert np.all(covered[identified]), detail
    # What the offline bench establishes for this very profile
    # (`python -m benchmarks chain --seeds 20 --json`: the same segments through the same service core, plant
    # noise seeds 0-19, this test's seed 3 among them; 2026-11-24): at 5000 rpm every H's 95 % CI covered the
    # truth in 20 of 20 seeds; H6, the best-determined H, had |error| at most 8.4 % (median 3.7 %); a seed's
    # median |error| over the seven H was at most 25.8 % (median 15.8 %). The live run differs only by
    # event-loop timing (which sample lands on a grid point, docs/design/service.md) and by its window (>= 35
    # min here, 40 in the bench). Asserted, with tolerances set from those figures and not from a run of this
    # test: - the CIs of H6 and H7 cover the truth (0 misses in 40 seed x H trials offline; 5 % each
    # nominally); - at least 6 of the 7 CIs cover the truth (7 in every seed offline; one miss allowed for the
    # timing); - H6's error within 1.5 x the bench's maximum (8.4 % -> 12.5 %);
    # - the median error over the seven H within 1.25 x the bench's worst seed (25.8 % -> 32 %).
    assert covered[5] and covered[6], detail
    assert covered.sum() >= 6, detail
    assert err[5] < 0.125, detail
    assert np.median(err) < 0.32, detail
