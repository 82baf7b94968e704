"""``chtc commission growth`` on a thermal test recorded on the virtual plant with drawn mechanics the service
does not know (``simulator.thermaltest``): the fit recovers them within their CIs, says where the model
fails when the test is corrupted, and the growth served with the calibration carries the mechanical
posterior in its CI."""

from __future__ import annotations

import hashlib
import json
from dataclasses import replace
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import pytest

from model.plant import Segment
from model.plantmech import mechanics_for_seed
from service.cli import main as cli_main
from service.contracts.mechanics import MechanicsCalibration
from service.estimate.growth import (
    FieldBelief,
    build_context,
    condition_terms,
    estimate_growth,
    with_mechanics,
)
from service.estimate.mechanics import served_mechanics_basis
from service.host.runtime import core_config
from service.modelload import LoadedModel
from service.settings import Settings
from service.shell.commissioning import (
    Displacements,
    field_history,
    fit_test,
    read_displacement_csv,
)
from simulator.thermaltest import ThermalTest, write_thermal_test

pytestmark = pytest.mark.slow  # a 80-min plant run (~5 s) and the service's core over it (~5 s)

SEED = 3  # drawn: restraint 0.683, α shaft 0.959, α housing 0.989
SHORT = (  # rest, one heat-up, a cool-down: the smallest test that pins the restraint
    Segment(600.0, 0.0, 0.0, 21.0),
    Segment(2400.0, 7000.0, 5.0, 21.0),
    Segment(1800.0, 0.0, 0.0, 21.0),
)


@pytest.fixture(scope="module")
def thermal_test(tmp_path_factory: pytest.TempPathFactory) -> ThermalTest:
    out = tmp_path_factory.mktemp("thermal-test")
    return write_thermal_test(out, mechanics=mechanics_for_seed(SEED), profile=SHORT, seed=SEED)


def test_the_shipped_example_is_this_test(thermal_test: ThermalTest) -> None:
    """service/data/example_thermal_test_*: ``python -m simulator.thermaltest OUT --short --seed 3``."""
    from drivers.logs import read_can_log, read_temperature_csv

    data = Path(__file__).resolve().parents[2] / "service" / "data"
    shipped = read_displacement_csv(data / "example_thermal_test_displacements.csv")
    made = read_displacement_csv(thermal_test.displacements)
    assert np.array_equal(shipped.t_s, made.t_s)
    assert np.allclose(shipped.axial_um, made.axial_um, atol=0.002, equal_nan=True)
    temps = read_temperature_csv(data / "example_thermal_test_temperatures.csv")
    assert np.allclose(temps.temps_c, read_temperature_csv(thermal_test.temperatures).temps_c, atol=0.011)
    assert len(read_can_log(data / "example_thermal_test_can.blf")) == len(read_can_log(thermal_test.canlog))


def test_the_cli_recovers_the_drawn_mechanics_within_their_ci(
    thermal_test: ThermalTest, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    t = thermal_test
    out = tmp_path / "report.json"
    argv = [
        "commission",
        "growth",
        str(t.temperatures),
        str(t.canlog),
        str(t.displacements),
        "--json",
        str(out),
    ]
    assert cli_main(argv) == 0, capsys.readouterr()
    text = capsys.readouterr().out
    assert "verdict: the model explains the test" in text and "prior 1σ" in text
    rep = json.loads(out.read_text())
    p = {q["name"]: q for q in rep["parameters"]}
    truth = {"restraint": t.mechanics.restraint, "alpha_shaft": t.mechanics.alpha_shaft}
    for name, value in truth.items():
        lo, hi = p[name]["ci95"]
        assert lo <= value <= hi, (name, value, p[name])
    assert p["restraint"]["sd"] < 0.5 * p["restraint"]["prior_sd"]  # the test pins it
    lo, hi = p["offset_um"]["ci95"]
    assert lo <= t.offset_um <= hi
    assert rep["explained"] and 0.0 < rep["residual_rms_um"] <= rep["residual_max_um"] < 3.0
    assert {ph["phase"].split()[0] for ph in rep["phases"]} == {"heat-up", "cool-down"}
    assert rep["sources"]["displacements"] == hashlib.sha256(t.displacements.read_bytes()).hexdigest()
    assert rep["timings_s"]["fit_s"] < 10.0
    # the test's zero is the spindle's uniform start temperature (21.0 °C here), not the first converged
    # field's mean (issue 41 item 14: 21.00 °C printed for a spindle uniform at 21.51 °C)
    assert rep["t_ref_c"] == pytest.approx(21.0, abs=0.06), rep["t_ref_c"]
    assert f"zero at {rep['t_ref_c']:.2f} °C" in text
    # the offset baseline of the test's 10-min rest (issue 40 part 3): this plant's sensors have no offsets
    b = rep["offset_baseline"]
    assert b["source"] == "auto" and b["samples"] >= 55 and len(b["offsets_c"]) == 32
    assert max(abs(v) for v in b["offsets_c"]) < 4.0 * max(b["sd_c"]) < 0.1
    assert "sensor offsets from the test's rest:" in text


@pytest.fixture(scope="module")
def fitted(thermal_test: ThermalTest, loaded_model: LoadedModel) -> tuple[object, object, Displacements]:
    hist = field_history(
        loaded_model, core_config(Settings()), thermal_test.temperatures, thermal_test.canlog
    )
    basis = served_mechanics_basis(loaded_model.spec, loaded_model.fe)
    return hist, basis, read_displacement_csv(thermal_test.displacements)


def test_a_test_the_model_cannot_explain_says_which_part_fails(
    fitted: tuple[object, object, Displacements], loaded_model: LoadedModel
) -> None:
    hist, basis, disp = fitted
    phi = np.asarray(loaded_model.rom.basis)
    _, ok, problems, _, _, _, _ = fit_test(basis, phi, hist, disp)  # type: ignore[arg-type]
    assert ok, problems
    # the fixture slipped by 4 µm at the stop: the fit can only absorb it in the set-up's drift, which says so
    t_stop = disp.t_s[0] + 3000.0
    slipped = replace(disp, axial_um=np.where(disp.t_s > t_stop, disp.axial_um + 4.0, disp.axial_um))
    _, ok, problems, _, _, _, _ = fit_test(basis, phi, hist, slipped)  # type: ignore[arg-type]
    assert not ok and any(p.startswith("drift_um_per_h = +") for p in problems), problems
    # 10 µm: the residuals too, in each phase
    slipped = replace(disp, axial_um=np.where(disp.t_s > t_stop, disp.axial_um + 10.0, disp.axial_um))
    _, ok, problems, _, _, _, _ = fit_test(basis, phi, hist, slipped)  # type: ignore[arg-type]
    assert not ok and any("fails in the cool-down" in p for p in problems), problems
    # no radial sensor: the axial series alone cannot separate the restraint from the shaft's α
    axial_only = replace(disp, radial_um=None)
    _, ok, problems, _, _, _, _ = fit_test(basis, phi, hist, axial_only)  # type: ignore[arg-type]
    assert not ok and any("no radial displacement" in p for p in problems)


def test_the_served_growth_uses_the_calibration_and_carries_its_posterior(
    fitted: tuple[object, object, Displacements], loaded_model: LoadedModel
) -> None:
    hist, basis, disp = fitted
    phi = np.asarray(loaded_model.rom.basis)
    joint, *_ = fit_test(basis, phi, hist, disp)  # type: ignore[arg-type]
    x, cov = joint.result.x[:3], joint.result.cov[:3, :3]
    m = loaded_model
    base = build_context(m.spec, m.fe, basis=m.rom.basis)
    ctx = with_mechanics(base, basis.operators_at(x), basis.jacobian_at(x), cov)  # type: ignore[attr-defined]
    terms = condition_terms(
        ctx, h=np.full(7, 50.0), cov_h=np.eye(7), ambient_c=21.0, q_front_w=0.0, q_rear_w=0.0
    )
    k = int(np.argmax(hist.states @ (ctx.g_phi[0])))  # type: ignore[attr-defined, index]
    belief = FieldBelief(state=hist.states[k], cov=np.zeros((phi.shape[1],) * 2))  # type: ignore[attr-defined]
    at = datetime(2026, 11, 27, 7, 0, tzinfo=UTC)
    est = estimate_growth(ctx, terms, belief, t_ref_c=21.0, at=at)
    base_terms = condition_terms(
        base, h=np.full(7, 50.0), cov_h=np.eye(7), ambient_c=21.0, q_front_w=0.0, q_rear_w=0.0
    )
    nominal = estimate_growth(base, base_terms, belief, t_ref_c=21.0, at=at)
    field = phi @ hist.states[k]  # type: ignore[attr-defined]
    assert est.axial.um == pytest.approx(float(basis.operators_at(x)[0] @ (field - 21.0)), abs=1e-6)  # type: ignore[attr-defined]
    assert abs(est.axial.um - nominal.axial.um) > 1.0  # the mount matters: s 0.68 against the TOML's free
    jac = np.einsum("opn,n->op", basis.jacobian_at(x), field - 21.0)  # type: ignore[attr-defined]
    assert est.axial.std_mech_um == pytest.approx(float(np.sqrt(jac[0] @ cov @ jac[0])), rel=1e-9)
    assert est.axial.std_mech_um > 0.0 and nominal.axial.std_mech_um == 0.0
    assert est.axial.std_um == pytest.approx(np.hypot(est.axial.std_h_um, est.axial.std_mech_um), rel=1e-9)
    # a fixture offset b measured by probe readings: added to the axial growth (now, forecast, steady), its
    # variance and its covariance with θ in the axial mechanical part; the radial growth untouched
    cb = np.array([0.004, -0.001, 0.002])  # Cov(θ, b) [µm]
    off = with_mechanics(base, basis.operators_at(x), basis.jacobian_at(x), cov, offset=(3.0, 0.25, cb))  # type: ignore[attr-defined]
    with_b = estimate_growth(off, terms, belief, t_ref_c=21.0, at=at)
    assert with_b.axial.um == pytest.approx(est.axial.um + 3.0, abs=1e-9)
    assert with_b.forecast.steady_axial.um == pytest.approx(est.forecast.steady_axial.um + 3.0, abs=1e-9)
    assert with_b.forecast.axial[0].um == pytest.approx(est.forecast.axial[0].um + 3.0, abs=1e-9)
    want = jac[0] @ cov @ jac[0] + 0.25 + 2.0 * jac[0] @ cb
    assert with_b.axial.std_mech_um == pytest.approx(float(np.sqrt(want)), rel=1e-9)
    assert with_b.radial.um == est.radial.um and with_b.radial.std_mech_um == est.radial.std_mech_um
    # at the zero's own uniform temperature nothing grows, whatever the mechanics
    flat = FieldBelief(mean_c=np.full(m.fe.n_nodes, 21.0))
    assert estimate_growth(ctx, terms, flat, t_ref_c=21.0, at=at).axial.std_mech_um == pytest.approx(
        0.0, abs=1e-9
    )


def test_the_growth_server_uses_a_restored_or_new_commissioning(
    fitted: tuple[object, object, Displacements], loaded_model: LoadedModel
) -> None:
    """``GrowthServer``: a shared context plus a restored calibration is calibrated on first use; a new
    commissioning replaces the operators and drops the condition terms computed with the old ones."""
    from service.serve.compensation import GrowthServer

    _, basis, _ = fitted
    m = loaded_model
    base = build_context(m.spec, m.fe, basis=m.rom.basis)
    cov = tuple(tuple(float(v) for v in row) for row in np.diag([0.04**2, 0.02**2, 0.05**2]))
    at = datetime(2026, 11, 27, 7, 0, tzinfo=UTC)
    cal = MechanicsCalibration(x=(0.6, 0.97, 1.0), cov=cov, at=at, set_by="t", source="cli")
    restored = GrowthServer(m, context=base, mechanics=cal, mechanics_basis=basis)  # type: ignore[arg-type]
    ctx = restored.prepare()
    assert ctx.g_mech is not None and np.allclose(ctx.g, basis.operators_at(cal.x))  # type: ignore[attr-defined]
    plain = GrowthServer(m, context=base, mechanics_basis=basis)  # type: ignore[arg-type]
    assert plain.prepare() is base and plain.mechanics is None
    old = plain.prepare()  # a term computed with the old operators is kept while they are current
    plain.terms.get(("key",), lambda: (object(), old), lambda: old)  # type: ignore[arg-type,return-value]
    assert ("key",) in plain.terms
    other = MechanicsCalibration(x=(0.2, 1.01, 0.99), cov=cov, at=at, set_by="t", source="api")
    plain.set_mechanics(other)
    assert plain.mechanics is other and ("key",) not in plain.terms
    assert np.allclose(plain.prepare().g, basis.operators_at(other.x))  # type: ignore[attr-defined]
