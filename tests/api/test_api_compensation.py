"""GET /compensation on the real service (``simulator.served``: the core and shell on their loop, a real
database) fed with virtual-plant samples: the served growth equals ``estimate_growth`` on the same inputs,
its status follows the /chtc rules (stale when data stop), and the dashboard shows it."""

from __future__ import annotations

import asyncio
import dataclasses
import re
from collections.abc import Iterator
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient

from api.app import create_app
from model.growth import Z95
from model.inputs import inputs_from_operation
from service.contracts.errors import NotReadyError
from service.core.machine import ServiceCore
from service.estimate.growth import build_context, condition_terms, estimate_growth
from service.estimate.growthterms import h_covariance, map_h_covariance
from service.host.runtime import core_config
from service.modelload import LoadedModel
from service.serve.compensation import GrowthServer, field_belief
from service.serve.policy import compensation_verdict
from service.settings import Settings
from service.shell.service import SoftSensorService
from simulator.served import ManualClock, served_service
from tests.api.conftest import MAP_MODE, LiveServer, served_map_mode, sqlite_url
from tests.api.test_api_dashboard import _chromium
from tests.engine_config import product_limits
from tests.modes import per_condition


@dataclass
class Served:
    model: LoadedModel
    svc: SoftSensorService
    clock: ManualClock
    client: TestClient
    t_start_c: float  # the provisional reference: the first converged live field's uniform equivalent [°C]
    t_start_sd_c: float  # its 1σ [°C]
    ready_before_request: bool  # the growth's terms were computed before any request


@pytest.fixture(scope="module")
def served(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Served]:
    """The real service on its loop (``simulator.served``), fed the whole demo plan (3000 then 4000 rpm), in
    per-condition mode (Σ_H from the record's CIs, ``h_covariance``; the map's: ``served_map`` below)."""
    url = sqlite_url(tmp_path_factory.mktemp("served-compensation"))
    with served_service(database_url=url, settings=per_condition(), feed_samples=1) as s:
        s.feed_next()
        assert s.service.view.current is not None, "no identification in the plant run"
        ready = s.service.growth.ready_for(s.service.view)
        assert s.service.growth.reference is None  # none stored, none configured: the provisional one
        ref = s.service.growth.reference_for(s.service.view)
        assert ref is not None
        t_start, t_start_sd = ref[0], ref[1]
        with TestClient(create_app(Settings(), s.service, clock=s.clock)) as client:
            yield Served(s.service.core.model, s.service, s.clock, client, t_start, t_start_sd, ready)


def _served_terms(model: Any, v: Any, h: np.ndarray, cov_h: np.ndarray) -> tuple[Any, Any]:
    """The growth context and the condition terms /compensation computes for the view's condition and H."""
    assert v.live is not None and v.condition is not None
    ctx = build_context(model.spec, model.fe, basis=model.rom.basis)
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
        cov_h=cov_h,
        ambient_c=float(inp.ambient_c[0]),
        q_front_w=float(inp.q_front_w[0]),
        q_rear_w=float(inp.q_rear_w[0]),
        load_scale=v.live.load_scale,
    )
    return ctx, terms


def test_served_growth_equals_estimate_growth_on_the_same_inputs(served: Served) -> None:
    body = served.client.get("/api/v1/compensation").json()
    v, model = served.svc.view, served.model
    assert v.live is not None and v.current is not None and v.condition is not None
    h = np.asarray(v.live.h, dtype=float)
    ctx, terms = _served_terms(model, v, h, h_covariance(v.current, h))
    belief = field_belief(v)
    at = datetime.fromtimestamp(v.live.t, tz=UTC)
    want = estimate_growth(
        ctx, terms, belief, t_ref_c=served.t_start_c, t_ref_sd_c=served.t_start_sd_c, at=at
    )
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


def test_the_verdict_is_the_policys_on_the_growth_and_goes_stale_when_data_stop(served: Served) -> None:
    """/compensation is judged on the growth (service.serve.policy.compensation_verdict), not copied from
    /chtc: the body carries exactly the policy's verdict on the served growth's CI."""
    client, clock = served.client, served.clock
    last = served.svc.view.newest
    assert last is not None
    comp = client.get("/api/v1/compensation").json()
    snap = served.svc.compensation()
    assert snap is not None
    lo, hi = comp["axial"]["ci95_um"]
    # the served service's limits: [compensation]'s defaults, without the mechanics and offset-baseline rules
    # on the simulator's plant (simulator.served: its mechanics match the spindle description, its sensors
    # have no offsets)
    limits = served.svc.growth.limits
    assert limits == dataclasses.replace(
        product_limits(), require_mechanics_calibration=False, require_offset_baseline=False
    )
    expected = compensation_verdict(
        served.svc.view,
        served.clock(),
        limits=limits,
        has_sample=True,
        ci95_half_um=0.5 * (hi - lo),
        identified_at=snap_identified_at(served),
        has_reference=False,  # none stored: no_reference unless something earlier already says no
    )
    assert comp["status"] == expected.status.value != "stale"
    assert comp["usable_for_compensation"] is expected.usable
    assert comp["reason_code"] == (None if expected.reason is None else expected.reason.value)
    assert (comp["action"] is None) is expected.usable
    # every blocking reason, in order, each with its action (issue 41 item 17)
    assert [b["reason_code"] for b in comp["blocking"]] == [b.reason.value for b in expected.blocking]
    assert [b["action"] for b in comp["blocking"]] == [b.action for b in expected.blocking]
    assert (
        comp["blocking"][:1]
        == [{"reason_code": comp["reason_code"], "reason": comp["reason"], "action": comp["action"]}]
        or expected.usable
    )
    limit = served.svc.view.stale_after_s
    try:
        clock.now = last.t + timedelta(seconds=limit - 1)
        assert client.get("/api/v1/compensation").json()["status"] != "stale"
        clock.now = last.t + timedelta(seconds=limit + 1)
        stale = client.get("/api/v1/compensation").json()
        assert stale["status"] == client.get("/api/v1/chtc").json()["status"] == "stale"
        assert client.get("/api/v1/compensation/section").json()["status"] == "stale"
        assert stale["usable_for_compensation"] is False and stale["reason"].startswith("stale:")
        assert stale["reason_code"] == "stale" and stale["action"]
        assert stale["sample_age_s"] == pytest.approx(limit + 1, abs=1e-3)
    finally:
        clock.now = last.t


def snap_identified_at(served: Served) -> datetime:
    rec = served.svc.view.current
    assert rec is not None
    return rec.finished_at


def test_nothing_to_serve_is_503_and_the_schema_is_in_openapi(tmp_path: Path) -> None:
    with served_service(database_url=sqlite_url(tmp_path), plan=None) as s:
        client = TestClient(create_app(Settings(), s.service, clock=s.clock))
        r = client.get("/api/v1/compensation")
        spec = client.get("/api/v1/openapi.json").json()
    assert r.status_code == 503 and r.json()["error"]["code"] == "no_data", r.text
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
            x
            for x in text.splitlines()
            if x.startswith(f'chtc_growth_um{{direction="{direction}",spindle="spindle1"}}')
        )
        assert float(line.split()[-1]) == pytest.approx(body[direction]["um"], abs=1e-3)
        lo, hi = body[direction]["ci95_um"]
        half = next(
            x
            for x in text.splitlines()
            if x.startswith(f'chtc_growth_ci95_half_width_um{{direction="{direction}",spindle="spindle1"}}')
        )
        assert float(half.split()[-1]) == pytest.approx(0.5 * (hi - lo), abs=1e-3)
    assert f'chtc_growth_status{{spindle="spindle1",status="{body["status"]}"}} 1.0' in text


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


def test_on_the_running_loop_the_terms_are_ready_before_the_first_request(served: Served) -> None:
    """The growth model is built at start and a new identification's terms are computed in a thread as
    soon as it is published (the fixture made no request before this was recorded)."""
    assert served.ready_before_request


def test_a_spindle_without_mechanics_serves_h_and_says_why_there_is_no_growth(served: Served) -> None:
    """The growth model is optional: without ``[mechanics]`` the service starts, and the growth is
    ``NotReadyError`` naming the cause (503 not_ready), not a crash."""
    bare = dataclasses.replace(served.model, spec=dataclasses.replace(served.model.spec, mechanics=None))
    server = GrowthServer(bare)
    with pytest.raises(NotReadyError, match="growth model unavailable"):
        server.snapshot(served.svc.view, served.clock())
    events: list[str] = []
    svc = SoftSensorService(
        ServiceCore(core_config(Settings()), model=bare), worker=None, on_event=events.append
    )

    async def start_and_close() -> None:
        await svc.start()
        await svc.close()

    asyncio.run(start_and_close())
    assert any(e.startswith("growth: unavailable growth model unavailable") for e in events), events


def test_section_is_the_live_fields_displacement_of_every_parts_outline(served: Served) -> None:
    """The served outline's displacement (the precomputed reduced operator) equals a full forward solve of
    the live field, and at the nose it is the served axial growth (the adjoint operator): two independent
    computations through the same K and B."""
    body = served.client.get("/api/v1/compensation/section").json()
    comp = served.client.get("/api/v1/compensation").json()
    v, model = served.svc.view, served.model
    assert v.live is not None
    assert body["unit"] == "µm" and body["at"] == comp["at"] and body["status"] == comp["status"]
    assert body["t_ref_c"] == comp["t_ref_c"] and body["identification_id"] == comp["identification_id"]
    assert body["at"].endswith("Z") or body["at"].endswith("+00:00")
    r, z = np.asarray(body["nodes_r_m"]), np.asarray(body["nodes_z_m"])
    u = np.array([body["u_r_um"], body["u_z_um"]])
    edges = np.asarray(body["edges"])
    assert edges.shape[1] == 2 and edges.min() == 0 and edges.max() == r.size - 1
    # every part is outlined: the shaft's axis (r = 0) from end to end, and the housing's outside (r = 100 mm)
    assert np.isclose(r, 0.0).sum() > 10 and np.isclose(r, 0.1).sum() > 10
    gm = build_context(model.spec, model.fe).growth
    t_ref = served.svc.growth.t_ref_c(v)  # served rounded to 1e-4 °C
    assert t_ref is not None and body["t_ref_c"] == pytest.approx(t_ref, abs=1e-4)
    full = gm.displacement_m(np.asarray(v.live.field_c), t_ref) * 1e6  # (Nm, 2)
    p = np.asarray(gm.solver.system.mesh.p).T
    for i in range(0, r.size, 7):  # nodes at one position: a floating surface's two sides; either matches
        at = np.flatnonzero(np.hypot(p[:, 0] - r[i], p[:, 1] - z[i]) < 1e-6)  # served to 0.1 µm
        assert at.size >= 1
        assert np.min(np.abs(full[at] - u[:, i]).max(axis=1)) < 2e-4, (r[i], z[i])
    nose = np.flatnonzero(np.isclose(r, 0.0) & np.isclose(z, z.max()))
    assert nose.size == 1
    assert u[1, nose[0]] == pytest.approx(comp["axial"]["um"], abs=2e-4)
    assert body["max_abs_um"] == pytest.approx(float(np.hypot(*u).max()), abs=1e-3)
    assert body["max_abs_um"] > comp["axial"]["um"] > 1.0  # the housing's rear end moves more than the nose


def test_the_reference_temperature_is_a_setting(tmp_path: Path, served: Served) -> None:
    """``compensation.reference_c``: the growth over a uniform 20 °C (a "config" zero, 1σ 0) instead of the
    provisional one. Linear: it differs from the provisional by Σg·(T_prov − 20) at the nose, and its CI
    lacks the provisional zero's 1σ."""
    default = served.client.get("/api/v1/compensation").json()
    assert default["reference"] is None and default["usable_for_compensation"] is False
    settings = per_condition(Settings(compensation={"reference_c": 20.0}))  # type: ignore[arg-type]  # as ``served``
    with served_service(database_url=sqlite_url(tmp_path), settings=settings) as s:
        client = TestClient(create_app(settings, s.service, clock=s.clock))
        body = client.get("/api/v1/compensation").json()
        section = client.get("/api/v1/compensation/section").json()
    assert body["at"] == default["at"], "the same plan, the same live field"
    assert body["t_ref_c"] == section["t_ref_c"] == 20.0
    assert body["reference"]["source"] == "config" and body["reference"]["sd_c"] == 0.0
    ctx = build_context(served.model.spec, served.model.fe)
    for row, name in enumerate(("axial", "radial")):
        g1 = float(ctx.g[row].sum())
        shift = g1 * (served.t_start_c - 20.0)
        assert body[name]["um"] == pytest.approx(default[name]["um"] + shift, abs=2e-3), name
        want_sd = np.sqrt(max(default[name]["std_um"] ** 2 - (g1 * served.t_start_sd_c) ** 2, 0.0))
        assert body[name]["std_um"] == pytest.approx(want_sd, abs=2e-3), name
    assert body["axial"]["um"] > default["axial"]["um"]  # a 22 °C start is warmer than 20 °C


@pytest.fixture(scope="module")
def served_map(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[SoftSensorService, TestClient]]:
    """The real service in speed-map mode (``tests.api.conftest.served_map_mode``, a duty cycle), fed its
    whole plan: the newest map fit was launched at 3500 rpm, the spindle has since moved to 4000 rpm."""
    with served_map_mode(tmp_path_factory.mktemp("served-compensation-map")) as s:
        s.feed_next()
        with TestClient(create_app(MAP_MODE, s.service, clock=s.clock)) as client:
            yield s.service, client


def test_in_map_mode_the_h_covariance_is_the_maps_at_the_current_speed(
    served_map: tuple[SoftSensorService, TestClient],
) -> None:
    svc, client = served_map
    body = client.get("/api/v1/compensation").json()
    v, model = svc.view, svc.core.model
    assert v.speed_map is not None and v.live is not None
    assert v.current is not None and v.condition is not None
    ambient, speed, _ = v.live.inputs
    assert abs(speed - v.current.condition.speed_rpm) >= 400.0, "the test needs a speed change since the fit"
    h = np.asarray(v.live.h, dtype=float)
    cov = map_h_covariance(v.speed_map, speed, ambient, h)
    # the same H as the live state's (the map at the current speed) and its band there, with the correlations
    h_map, _, hi = v.speed_map.h_at([speed], ambient)
    np.testing.assert_allclose(h, h_map[0], rtol=1e-9)
    np.testing.assert_allclose(np.sqrt(np.diag(cov)) / h, np.log(hi[0] / h) / Z95, rtol=1e-6)
    assert np.count_nonzero(np.abs(cov - np.diag(np.diag(cov))) > 1e-9 * np.max(cov)) > 0
    # ... not the stored fit's band at its launch speed (what /compensation used before)
    old = h_covariance(v.current, h)
    assert np.max(np.abs(np.sqrt(np.diag(cov)) / np.sqrt(np.diag(old)) - 1.0)) > 0.05
    ctx, terms = _served_terms(model, v, h, cov)
    ref = svc.growth.reference_for(v)  # the provisional zero (none stored) and its 1σ
    assert ref is not None and body["t_ref_c"] == pytest.approx(ref[0], abs=1e-4)
    at = datetime.fromtimestamp(v.live.t, tz=UTC)
    want = estimate_growth(ctx, terms, field_belief(v), t_ref_c=ref[0], t_ref_sd_c=ref[1], at=at)
    for name, w in (("axial", want.axial), ("radial", want.radial)):
        assert body[name]["um"] == pytest.approx(w.um, abs=1e-4), name
        assert body[name]["ci95_um"] == pytest.approx(list(w.ci95_um), abs=1e-4), name
    steady = body["forecast"]["steady_axial"]
    assert steady["ci95_um"] == pytest.approx(list(want.forecast.steady_axial.ci95_um), abs=1e-4)


def test_the_command_value_is_served_in_each_controllers_unit(served: Served) -> None:
    """Issue 42: /compensation serves what the controller applies now (the gate's and the command's state
    stepped on the service's clock), bounded by the profile, in each controller's unit."""
    client = served.client
    comp = client.get("/api/v1/compensation").json()
    cmd = comp["command"]
    assert cmd is not None and cmd["profile"]["name"] == "generic"
    prof = served.svc.growth.controller.limits.profile  # type: ignore[union-attr]
    assert abs(cmd["value_um"]) <= prof.limit_um
    assert cmd["status"] in ("following", "rate_limited", "holding", "fading", "at_limit", "none")
    corr = -comp["plc"]["tool_dir"] * cmd["value_um"]
    assert cmd["correction_um"] == pytest.approx(corr, abs=1e-3)
    assert cmd["sd43900_temp_comp_abs_value_mm"] == pytest.approx(corr * 1e-3, abs=1e-6)
    assert cmd["fanuc_is_c_units"] == round(10.0 * cmd["correction_um"])
    # the plain verdict here is no_reference (a safety reason): the command is not following the growth
    assert comp["reason_code"] != "ci_too_wide" or cmd["status"] != "following"
    snap = served.svc.compensation()
    assert snap is not None and snap.policy_verdict is not None
    assert snap.verdict.reason == snap.policy_verdict.reason or snap.policy_verdict.reason is None


def test_the_live_checkpoint_carries_the_command_state() -> None:
    from types import SimpleNamespace

    from service.contracts.checkpoint import LiveCheckpoint
    from service.contracts.verdict import ChtcStatus, Verdict
    from service.core.config import control_limits
    from service.serve.controlled import Controller, ControlState
    from service.shell.internal import with_control

    ctl = Controller(control_limits(Settings()))
    ctl.step(100.0, Verdict(ChtcStatus.FRESH, True), growth_um=3.0, half_um=1.0)
    r = 2
    cp = LiveCheckpoint(
        t=100.0,
        model_version="m",
        converged=True,
        inputs=(20.0, 0.0, 0.0),
        mean=np.zeros(r),
        cov=np.eye(r),
        cross=np.zeros((r, 9)),
        bias_s=np.zeros((r, 3)),
        bias_m=np.zeros((r, r)),
    )
    out = with_control(cp, SimpleNamespace(controller=ctl))  # type: ignore[arg-type]
    assert isinstance(out, LiveCheckpoint)
    back = LiveCheckpoint.from_parts(
        out.to_bytes(), t=100.0, model_version="m", converged=True, inputs=cp.inputs
    )
    assert ControlState.from_array(back.control) == ctl.state
    assert with_control(cp, SimpleNamespace(controller=None)) is cp  # type: ignore[arg-type]
