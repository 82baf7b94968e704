"""Growth uncertainty and sensor sensitivity: exact propagation checked against sampling and differences."""

from __future__ import annotations

import numpy as np
import pytest

from model.fem import FEModel, steady_state
from model.geometry import SpindleSpec
from model.growth import (
    Z95,
    GrowthError,
    ci95,
    growth_std_um,
    h_growth_std_um,
    reconstruction_basis,
    reconstruction_h_fit,
    sensor_sensitivity,
    steady_jacobian_h,
)
from model.heat import bearing_heat_w
from model.thermoelastic import GrowthModel
from tests.model_growth.conftest import H_TABLE4

AMB = 20.0


def _heats(spec: SpindleSpec) -> dict[str, float]:
    return {
        "ambient_c": AMB,
        "q_front_w": float(bearing_heat_w(5000.0, 0.0, spec.bearings.front)),
        "q_rear_w": float(bearing_heat_w(5000.0, 0.0, spec.bearings.rear)),
    }


def test_std_from_factor_nodal_and_reduced_agree_with_sampling(fe: FEModel, growth: GrowthModel) -> None:
    rng = np.random.default_rng(7)
    r, z = fe.nodes_rz.T
    u = np.column_stack([np.ones(fe.n_nodes), z / 0.61, r / 0.1, np.sin(9 * z)]) * [0.3, 0.5, 0.2, 0.1]
    std_factor = growth_std_um(growth.operators, factor=u)
    std_reduced = growth_std_um(growth.operators, cov=np.eye(4), phi=u)  # field = U a, Cov a = I
    assert np.allclose(std_factor, std_reduced, rtol=1e-12)
    ys = [growth.growth_um(rng.standard_normal((1000, 4)) @ u.T, 0.0) for _ in range(20)]  # Cov = U U^T
    sampled = np.std(np.concatenate(ys), axis=0)
    assert np.allclose(std_factor, sampled, rtol=0.03)


def test_nodal_covariance_on_a_small_field(growth: GrowthModel) -> None:
    g = growth.operators[:, :50]
    rng = np.random.default_rng(8)
    a = rng.normal(size=(50, 50))
    cov = a @ a.T
    want = np.sqrt(np.diag(g @ cov @ g.T))
    assert np.allclose(growth_std_um(g, cov=cov), want, rtol=1e-12)
    assert np.allclose(growth_std_um(g, factor=a), want, rtol=1e-12)
    with pytest.raises(GrowthError, match="cov"):
        growth_std_um(g, cov=cov[:-1])
    with pytest.raises(GrowthError, match="cov"):
        growth_std_um(g)


def test_ci95_is_plus_minus_1_96_sigma() -> None:
    lo, hi = ci95(10.0, 2.0)
    assert (lo, hi) == pytest.approx((10.0 - 2 * Z95, 10.0 + 2 * Z95))
    assert abs(Z95 - 1.959964) < 1e-6


def test_h_jacobian_matches_central_differences(spec: SpindleSpec, fe: FEModel, growth: GrowthModel) -> None:
    cond = _heats(spec)
    jac = steady_jacobian_h(fe, H_TABLE4, **cond)
    g = growth.operator("nose_axial")
    for i in (0, 4, 6):
        step = np.zeros(7)
        step[i] = 1e-3 * H_TABLE4[i]
        plus = steady_state(fe, np.add(H_TABLE4, step), **cond)
        minus = steady_state(fe, np.subtract(H_TABLE4, step), **cond)
        fd = g @ (plus - minus) / (2 * step[i])
        assert g @ jac[:, i] == pytest.approx(fd, rel=1e-5)
    cov_h = np.diag((0.1 * np.asarray(H_TABLE4)) ** 2)  # 10 % 1-sigma on every H, uncorrelated
    std = h_growth_std_um(growth.operators, jac, cov_h)
    assert std[0] == pytest.approx(np.sqrt(np.sum((g @ jac * 0.1 * np.asarray(H_TABLE4)) ** 2)), rel=1e-12)


def test_h_fit_reconstruction_is_exact_for_fields_it_can_explain(
    spec: SpindleSpec, fe: FEModel, growth: GrowthModel
) -> None:
    jac = steady_jacobian_h(fe, H_TABLE4, **_heats(spec))
    recon = reconstruction_h_fit(fe, jac)
    dh = np.array([3.0, -2.0, 1.0, 0.5, -4.0, 2.0, 1.5])
    dy = fe.sensor_op @ (jac @ dh)  # the sensors of an H change
    sens = sensor_sensitivity(growth.operators, recon)
    assert sens.shape == (len(growth.names), 32)
    assert np.allclose(sens @ dy, growth.operators @ (jac @ dh), rtol=1e-6)


def test_basis_reconstruction_recovers_fields_in_its_span(fe: FEModel, growth: GrowthModel) -> None:
    r, z = fe.nodes_rz.T
    phi = np.column_stack([np.ones_like(r), z, r, z * r, np.cos(8 * z)])
    a = np.array([2.0, -1.0, 3.0, 0.5, 0.7])
    recon = reconstruction_basis(phi, fe.sensor_op)
    assert np.allclose(recon @ (fe.sensor_op @ (phi @ a)), phi @ a, rtol=1e-8, atol=1e-10)


def test_map_fit_tends_to_least_squares_and_to_the_prior(
    spec: SpindleSpec, fe: FEModel, growth: GrowthModel
) -> None:
    jac = steady_jacobian_h(fe, H_TABLE4, **_heats(spec))
    ls = sensor_sensitivity(growth.operators, reconstruction_h_fit(fe, jac))
    wide = reconstruction_h_fit(fe, jac, noise_c=0.15, prior_cov_h=np.eye(7) * 1e12)
    tight = reconstruction_h_fit(fe, jac, noise_c=0.15, prior_cov_h=np.eye(7) * 1e-12)
    assert np.allclose(sensor_sensitivity(growth.operators, wide), ls, rtol=1e-4, atol=1e-6)
    assert np.max(np.abs(sensor_sensitivity(growth.operators, tight))) < 1e-9
    with pytest.raises(GrowthError, match="prior_cov_h"):
        reconstruction_h_fit(fe, jac, noise_c=0.15)
