"""The mechanics fit (``model.growthfit``) on a synthetic thermal test from a drawn plant's mechanics."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest

from model.fem import FEModel, make_stepper
from model.geometry import SpindleSpec
from model.growthfit import (
    PARAMS,
    GrowthFitError,
    MechanicsBasis,
    MechanicsPrior,
    features,
    fit_mechanics,
    mechanics_basis,
)
from model.inputs import InputSeries, inputs_from_operation
from model.plant import H_TABLE4
from model.plantmech import PlantMechanics, build_plant_growth

DT_S = 60.0
T0_C = 20.0
# an ISO 230-3-like test: heat-up at two speeds, then cool-down at rest (H: Table 4 scaled, for the test)
TEST = ((90, 6000.0, 1.3), (60, 3000.0, 1.0), (120, 0.0, 0.6))  # (minutes, rpm, H factor)


@dataclass(frozen=True)
class Run:
    times_s: np.ndarray
    fields_c: np.ndarray  # (n, N)


def _march(spec: SpindleSpec, fe: FEModel, segments: tuple[tuple[int, float, float], ...]) -> Run:
    t = np.full(fe.n_nodes, T0_C)
    out = [t]
    for minutes, rpm, hf in segments:
        inp = inputs_from_operation(
            spec, dt_s=DT_S, speed_rpm=np.full(minutes, rpm), torque_nm=5.0, ambient_c=T0_C
        )
        series = InputSeries(
            dt_s=DT_S, ambient_c=inp.ambient_c, q_front_w=inp.q_front_w, q_rear_w=inp.q_rear_w
        )
        fields, _ = make_stepper(fe, np.asarray(H_TABLE4) * hf, dt_s=DT_S).march(series, t)
        out.extend(fields[1:])
        t = fields[-1]
    f = np.array(out)
    return Run(times_s=np.arange(f.shape[0]) * DT_S, fields_c=f)


@pytest.fixture(scope="module")
def basis(spec: SpindleSpec, fe: FEModel) -> MechanicsBasis:
    return mechanics_basis(spec, fe)


@pytest.fixture(scope="module")
def test_run(spec: SpindleSpec, fe: FEModel) -> Run:
    return _march(spec, fe, TEST)


@pytest.fixture(scope="module")
def check_run(spec: SpindleSpec, fe: FEModel) -> Run:
    """Another duty (not the test's): 4500 rpm then 1500 rpm, to judge the fitted model."""
    return _march(spec, fe, ((60, 4500.0, 1.1), (60, 1500.0, 0.8)))


def _plant_growth(spec: SpindleSpec, fe: FEModel, mech: PlantMechanics, run: Run) -> np.ndarray:
    gm = build_plant_growth(spec, fe, mech)  # the plant: a radial spring on the face, not the fit's blend
    return np.asarray(gm.growth_um(run.fields_c, T0_C)[:, gm.names.index("nose_axial")])


def test_basis_reproduces_the_free_and_held_growth(
    spec: SpindleSpec, fe: FEModel, basis: MechanicsBasis
) -> None:
    rng = np.random.default_rng(3)
    field = T0_C + rng.uniform(0, 10, size=fe.n_nodes)
    for s in (0.0, 1.0):
        mech = PlantMechanics(restraint=s, alpha_shaft=1.03, alpha_housing=0.96)
        expected = build_plant_growth(spec, fe, mech).growth_um(field, T0_C)[0]
        got = basis.growth_um(field, T0_C, restraint=s, alpha_shaft=1.03, alpha_housing=0.96)
        np.testing.assert_allclose(got, expected, atol=1e-9)


@pytest.mark.parametrize(
    "mech",
    [
        PlantMechanics(restraint=0.36, alpha_shaft=1.017, alpha_housing=1.0),  # seed 301's draw
        PlantMechanics(restraint=0.8, alpha_shaft=0.96, alpha_housing=1.04),
    ],
)
def test_fit_recovers_a_drawn_plant(
    spec: SpindleSpec,
    fe: FEModel,
    basis: MechanicsBasis,
    test_run: Run,
    check_run: Run,
    mech: PlantMechanics,
) -> None:
    rng = np.random.default_rng(11)
    offset, drift, noise = 2.5, 0.6, 0.2  # µm, µm/h, µm
    truth = _plant_growth(spec, fe, mech, test_run)
    y = truth + offset + drift * test_run.times_s / 3600.0 + noise * rng.standard_normal(truth.size)
    y[rng.choice(y.size, 15, replace=False)] = np.nan  # missing values
    fit = fit_mechanics(features(basis, test_run.fields_c, T0_C), test_run.times_s, y)
    assert fit.success and fit.n_used == y.size - 15
    assert fit.residual_rms_um < 1.5 * noise  # the blend explains the spring within the noise
    est = fit.as_dict()
    assert abs(est["restraint"] - mech.restraint) < 0.1
    assert abs(est["offset_um"] - offset) < 0.5 and abs(est["drift_um_per_h"] - drift) < 0.3
    assert np.all(fit.sd > 0) and np.all(fit.sd[:3] < fit.prior_sd[:3])  # the test informs every parameter
    # what matters: on another duty, the fitted model's growth is close to the plant's; the nominal is not
    other = _plant_growth(spec, fe, mech, check_run)
    fitted = basis.growth_um(
        check_run.fields_c,
        T0_C,
        restraint=est["restraint"],
        alpha_shaft=est["alpha_shaft"],
        alpha_housing=est["alpha_housing"],
    )
    nominal = basis.growth_um(check_run.fields_c, T0_C, restraint=0.0)
    assert np.max(np.abs(fitted - other)) < 0.3
    assert np.max(np.abs(nominal - other)) > 2.0


def test_fit_of_the_nominal_plant_stays_at_the_nominal(
    spec: SpindleSpec, fe: FEModel, basis: MechanicsBasis, test_run: Run
) -> None:
    truth = _plant_growth(spec, fe, PlantMechanics(), test_run)
    fit = fit_mechanics(features(basis, test_run.fields_c, T0_C), test_run.times_s, truth, noise_um=0.05)
    assert fit.x[0] < 0.02
    np.testing.assert_allclose(fit.x[1:3], 1.0, atol=0.01)
    np.testing.assert_allclose(fit.x[3:], 0.0, atol=0.05)
    assert fit.residual_max_um < 0.05


def test_bad_inputs_are_named(basis: MechanicsBasis, test_run: Run) -> None:
    f = features(basis, test_run.fields_c, T0_C)
    with pytest.raises(GrowthFitError, match="displacement_um"):
        fit_mechanics(f, test_run.times_s, np.zeros(3))
    with pytest.raises(GrowthFitError, match="usable samples"):
        fit_mechanics(f[:5], test_run.times_s[:5], np.zeros(5))
    with pytest.raises(GrowthFitError, match=r"prior\.alpha_shaft"):
        MechanicsPrior(alpha_shaft=(1.0, 0.0))
    assert len(PARAMS) == 5
