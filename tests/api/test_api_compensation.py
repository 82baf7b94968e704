"""GET /compensation on the real service (SoftSensorService around a real ServiceCore, jobs inline) fed with
virtual-plant samples: the served growth equals ``estimate_growth`` on the same inputs, its status follows
the /chtc rules (stale when data stop), and the dashboard shows it."""

from __future__ import annotations

import asyncio
import dataclasses
import re
import time
from collections.abc import Iterator
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient

from api.app import create_app
from model.geometry import load_spindle
from model.inputs import inputs_from_operation
from model.plant import Segment, VirtualPlant
from service.engine.core import CoreConfig, ServiceCore
from service.engine.growthserve import GrowthServer, field_belief, h_covariance
from service.engine.shell import SoftSensorService
from service.estimate.growth import build_context, condition_terms, estimate_growth
from service.identify.detector import DetectorConfig
from service.identify.scheduler import SchedulerConfig
from service.identify.window import WindowRules
from service.identify.worker import run_job
from service.modelload import LoadedModel, ModelRef, load_model
from service.serve.interface import NotReadyError
from service.settings import Settings
from service.sim.logsamples import samples_from_plant
from tests.api.conftest import LiveServer, ManualClock
from tests.api.test_api_dashboard import _chromium

CFG = CoreConfig(
    detector=DetectorConfig(hold_s=60.0),
    scheduler=SchedulerConfig(min_data_s=600.0, schedule_s=(600.0, 1200.0), max_window_s=3600.0),
    rules=WindowRules(dt_s=10.0, min_window_s=600.0, min_good_channels=24),
    calibration=None,
)
T0 = datetime(2026, 1, 5, 8, 0, 0, tzinfo=UTC).timestamp()


@dataclass
class Served:
    model: LoadedModel
    svc: SoftSensorService
    clock: ManualClock
    client: TestClient
    t_start_c: float  # the live state's start temperature (the reference)


@pytest.fixture(scope="module")
def served() -> Iterator[Served]:
    model = load_model(ModelRef.from_settings(Settings().model))
    plant = VirtualPlant(load_spindle(), mesh_size_m=0.004, seed=5)
    run = plant.run([Segment(600.0, 0.0, 0.0, 22.0), Segment(1500.0, 4000.0, 8.0, 22.0)])
    samples = samples_from_plant(run, t0_s=T0)
    clock = ManualClock(samples[0].t)
    core = ServiceCore(CFG, model=model)
    svc = SoftSensorService(core, worker=None, clock=clock, run_job=lambda r: run_job(model, r))
    t_start: float | None = None
    for s in samples:
        clock.now = s.t
        svc.on_sample(s)
        if t_start is None and svc.view.live is not None:
            t_start = float(np.mean(svc.view.live.field_c))
    assert t_start is not None and svc.view.current is not None, "no identification in the plant run"
    with TestClient(create_app(Settings(), svc, clock=clock)) as client:
        yield Served(model, svc, clock, client, t_start)


def test_served_growth_equals_estimate_growth_on_the_same_inputs(served: Served) -> None:
    body = served.client.get("/api/v1/compensation").json()
    v, model = served.svc.view, served.model
    assert v.live is not None and v.current is not None and v.condition is not None
    ctx = build_context(model.spec, model.fe, basis=model.rom.basis)
    h = np.asarray(v.live.h, dtype=float)
    inp = inputs_from_operation(
        model.spec,
        dt_s=10.0,
        speed_rpm=v.condition.speed_rpm,
        torque_nm=v.condition.torque_nm,
        ambient_c=v.condition.ambient_c,
    )
    terms = condition_terms(
        ctx,
        h=h,
        cov_h=h_covariance(v.current, h),
        ambient_c=float(inp.ambient_c[0]),
        q_front_w=float(inp.q_front_w[0]),
        q_rear_w=float(inp.q_rear_w[0]),
        load_scale=v.live.load_scale,
    )
    belief = field_belief(model, v, served.svc.core.live_covariance)
    at = datetime.fromtimestamp(v.live.t, tz=UTC)
    want = estimate_growth(ctx, terms, belief, t_ref_c=served.t_start_c, at=at)
    assert datetime.fromisoformat(body["at"]) == at
    assert body["t_ref_c"] == pytest.approx(served.t_start_c, abs=1e-4)
    for name, w in (("axial", want.axial), ("radial", want.radial)):
        got = body[name]
        assert got["um"] == pytest.approx(w.um, abs=1e-4), name
        assert got["ci95_um"] == pytest.approx(list(w.ci95_um), abs=1e-4), name
        assert got["plc_0p1um"] == w.plc_0p1um == round(10 * w.um), name
        assert abs(got["plc_0p1um"] / 10 - got["um"]) <= 0.05 + 1e-9, name
        assert got["std_um"] > 0, name
    # a warm spindle (4000 rpm for 25 min over a cold reference) has grown towards the tool
    assert body["axial"]["um"] > 1.0
    fc = body["forecast"]
    assert [hz["horizon_s"] for hz in fc["horizons"]] == [300.0, 900.0, 1800.0]
    for got, w in zip(fc["horizons"], want.forecast.axial, strict=True):
        assert got["axial"]["um"] == pytest.approx(w.um, abs=1e-4)
        assert datetime.fromisoformat(got["at"]) == at + timedelta(seconds=got["horizon_s"])
    assert fc["steady_axial"]["um"] == pytest.approx(want.forecast.steady_axial.um, abs=1e-4)
    assert fc["tau_s"] == pytest.approx(want.forecast.tau_s, abs=0.1)
    plc = body["plc"]
    assert plc["tool_dir"] == -1
    # the tool points to -Z: a growth +δ towards the tool needs an axis correction of +δ
    assert plc["correction_um"] == pytest.approx(want.axial.um, abs=1e-4)
    assert plc["isg_temp_comp_offset_0_0p1um"] == round(10 * want.axial.um)
    assert plc["sd43900_temp_comp_abs_value_mm"] == pytest.approx(want.axial.um * 1e-3, abs=1e-7)
    assert plc["sd42960_tool_temp_comp_mm"] == pytest.approx(want.axial.um * 1e-3, abs=1e-7)
    assert [s["channel"] for s in body["sensitivity"]] == [s.channel for s in model.spec.sensors]
    np.testing.assert_allclose(
        [s["axial_um_per_c"] for s in body["sensitivity"]], want.sensitivity_axial_um_per_k, atol=1e-5
    )
    assert body["identification_id"] == v.current.id


def test_status_and_usability_are_those_of_chtc_and_go_stale_when_data_stop(served: Served) -> None:
    client, clock = served.client, served.clock
    last = served.svc.view.newest
    assert last is not None
    chtc = client.get("/api/v1/chtc").json()
    comp = client.get("/api/v1/compensation").json()
    assert comp["status"] == chtc["status"] and comp["status"] != "stale"
    assert comp["usable_for_compensation"] == chtc["usable_for_compensation"]
    assert comp["reason"] == chtc["reason"]
    limit = served.svc.view.stale_after_s
    try:
        clock.now = last.t + timedelta(seconds=limit - 1)
        assert client.get("/api/v1/compensation").json()["status"] != "stale"
        clock.now = last.t + timedelta(seconds=limit + 1)
        stale = client.get("/api/v1/compensation").json()
        assert stale["status"] == client.get("/api/v1/chtc").json()["status"] == "stale"
        assert stale["usable_for_compensation"] is False and stale["reason"].startswith("stale:")
        assert stale["sample_age_s"] == pytest.approx(limit + 1, abs=1e-3)
    finally:
        clock.now = last.t


def test_nothing_to_serve_is_503_and_the_schema_is_in_openapi() -> None:
    model = load_model(ModelRef.from_settings(Settings().model))
    svc = SoftSensorService(ServiceCore(CFG, model=model), worker=None, run_job=lambda r: run_job(model, r))
    client = TestClient(create_app(Settings(), svc))
    r = client.get("/api/v1/compensation")
    assert r.status_code == 503 and r.json()["error"]["code"] == "no_data", r.text
    spec = client.get("/api/v1/openapi.json").json()
    ref = spec["paths"]["/api/v1/compensation"]["get"]["responses"]["200"]["content"]["application/json"]
    name = ref["schema"]["$ref"].rsplit("/", 1)[1]
    props = spec["components"]["schemas"][name]["properties"]
    for key in ("status", "usable_for_compensation", "axial", "radial", "forecast", "plc", "sensitivity"):
        assert key in props, key


def test_metrics_carry_the_served_growth(served: Served) -> None:
    body = served.client.get("/api/v1/compensation").json()
    text = served.client.get("/api/v1/metrics").text
    for direction in ("axial", "radial"):
        line = next(
            x for x in text.splitlines() if x.startswith(f'chtc_growth_um{{direction="{direction}"}}')
        )
        assert float(line.split()[-1]) == pytest.approx(body[direction]["um"], abs=1e-3)
        lo, hi = body[direction]["ci95_um"]
        half = next(
            x
            for x in text.splitlines()
            if x.startswith(f'chtc_growth_ci95_half_width_um{{direction="{direction}"}}')
        )
        assert float(half.split()[-1]) == pytest.approx(0.5 * (hi - lo), abs=1e-3)
    assert f'chtc_growth_status{{status="{body["status"]}"}} 1.0' in text


@pytest.mark.browser
def test_dashboard_growth_panel_shows_the_served_value(
    chromium_path: str, tmp_path: Path, served: Served
) -> None:
    body = served.client.get("/api/v1/compensation").json()
    with LiveServer(create_app(Settings(), served.svc, clock=served.clock)) as server:
        dom = _chromium(chromium_path, tmp_path, server.url + "/", "--window-size=1400,1600", "--dump-dom")
    shown = re.search(r'id="growth-axial">([^<]*)<', dom)
    assert shown is not None, re.findall(r'id="growth-now"[^\n]{0,300}', dom)
    assert shown.group(1) == f"{body['axial']['um']:.1f}"
    assert re.search(r'id="growth-chart"[^>]*data-points="1"', dom), re.findall(
        r'<canvas id="growth-chart"[^>]*>', dom
    )
    assert "axial growth, µm" in dom


def test_on_the_running_loop_the_terms_are_ready_before_the_first_request() -> None:
    """With a loop (the running service), the growth model is built at start and a new identification's
    terms are computed in a thread as soon as it is published, not by the request."""
    model = load_model(ModelRef.from_settings(Settings().model))
    run = VirtualPlant(load_spindle(), mesh_size_m=0.004, seed=6).run(
        [Segment(300.0, 0.0, 0.0, 22.0), Segment(1200.0, 3000.0, 6.0, 22.0)]
    )
    samples = samples_from_plant(run, t0_s=T0)
    clock = ManualClock(samples[0].t)
    svc = SoftSensorService(
        ServiceCore(CFG, model=model), worker=None, clock=clock, run_job=lambda r: run_job(model, r)
    )

    async def drive() -> bool:
        await svc.start()
        try:
            for s in samples:
                clock.now = s.t
                svc.on_sample(s)
                await asyncio.sleep(0)
            deadline = time.monotonic() + 30.0
            while not svc.growth.ready_for(svc.view) and time.monotonic() < deadline:
                await asyncio.sleep(0.05)
            return svc.growth.ready_for(svc.view)
        finally:
            await svc.close()

    assert asyncio.run(drive()), "the terms were not computed off the request"
    assert svc.view.current is not None
    snap = svc.compensation()
    assert snap is not None and snap.identification_id == svc.view.current.id


def test_a_spindle_without_mechanics_serves_h_and_says_why_there_is_no_growth(served: Served) -> None:
    """The growth model is optional: without ``[mechanics]`` the service starts, and the growth is
    ``NotReadyError`` naming the cause (503 not_ready), not a crash."""
    bare = dataclasses.replace(served.model, spec=dataclasses.replace(served.model.spec, mechanics=None))
    server = GrowthServer(bare, served.svc.core.live_covariance)
    with pytest.raises(NotReadyError, match="growth model unavailable"):
        server.snapshot(served.svc.view, served.svc.chtc)
    events: list[str] = []
    svc = SoftSensorService(ServiceCore(CFG, model=bare), worker=None, on_event=events.append)

    async def start_and_close() -> None:
        await svc.start()
        await svc.close()

    asyncio.run(start_and_close())
    assert any(e.startswith("growth: unavailable growth model unavailable") for e in events), events
