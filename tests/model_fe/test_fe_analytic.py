"""FE model against closed forms: radial conduction, lumped transient, energy balance, affine assembly."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.sparse.linalg import spsolve
from skfem import BilinearForm, ElementTriP1, FacetBasis, MeshTri

from model.fem import (
    FEError,
    build_fe_model,
    load_vector,
    simulate,
    simulate_sensors,
    steady_state,
    stiffness,
)
from model.geometry import spec_from_dict
from model.inputs import InputSeries

from .cases import A_M, B_M, L_M, cylinder_doc

Q_VOL = 2.0e5  # W/m^3
K = 40.0
H_OUT = 25.0
TI = 20.0


def radial_exact(r: np.ndarray) -> np.ndarray:
    """Hollow cylinder, uniform source, adiabatic inside, Robin (H_OUT, TI) outside."""
    q, a, b = Q_VOL, A_M, B_M
    return (
        TI
        + q / (4 * K) * (b**2 - r**2)
        + q * a**2 / (2 * K) * np.log(r / b)
        + q * (b**2 - a**2) / (2 * b * H_OUT)
    )


def radial_fe_error(size: float, *, align: bool) -> float:
    spec = spec_from_dict(cylinder_doc(k=K))
    fe = build_fe_model(spec, mesh_size_m=size, align=align)
    half_volume = np.pi * (B_M**2 - A_M**2) * L_M / 2
    h = np.array([0.0, H_OUT, 0, 0, 0, 0, 0])
    T = steady_state(fe, h, ambient_c=TI, q_front_w=Q_VOL * half_volume, q_rear_w=Q_VOL * half_volume)
    r = np.array([s.r_m for s in spec.sensors])
    return float(np.abs(fe.sensors(T) - radial_exact(r)).max())


def test_radial_conduction_matches_closed_form() -> None:
    rise = radial_exact(np.array([A_M]))[0] - TI
    assert rise > 5.0  # the check is not trivial
    assert radial_fe_error(0.0025, align=False) < 2e-3 * rise


def test_point_error_converges_at_second_order() -> None:
    errors = [radial_fe_error(s, align=False) for s in (0.005, 0.0025, 0.00125)]
    rates = np.log2(np.array(errors[:-1]) / np.array(errors[1:]))
    assert np.all(rates > 1.7), (errors, rates)


def test_transient_lumped_limit() -> None:
    rho, c, h = 7800.0, 460.0, 5.0
    spec = spec_from_dict(cylinder_doc(k=1e5, rho=rho, c=c))
    fe = build_fe_model(spec, mesh_size_m=0.005)
    volume = np.pi * (B_M**2 - A_M**2) * L_M
    area = 2 * np.pi * (A_M + B_M) * L_M + 2 * np.pi * (B_M**2 - A_M**2)
    assert fe.zone_area_m2.sum() == pytest.approx(area, rel=1e-12)
    tau = rho * c * volume / (h * area)
    dt, n = 60.0, 200
    inputs = InputSeries.constant(n, dt_s=dt, ambient_c=TI, q_front_w=0.0, q_rear_w=0.0)
    fields = simulate(fe, np.full(7, h), inputs, 80.0)
    mean = fields.mean(axis=1)
    k = np.arange(n + 1)
    discrete_be = TI + (80.0 - TI) * (1 + dt / tau) ** (-k)
    assert np.abs(mean - discrete_be).max() < 1e-3
    assert np.abs(mean - (TI + 60.0 * np.exp(-k * dt / tau))).max() < 0.2  # BE O(dt) vs exact exponential
    assert np.ptp(fields[-1]) < 1e-3  # Biot ~ 1e-6: uniform


def test_energy_balance_at_steady_state(coarse_fe, spec) -> None:  # type: ignore[no-untyped-def]
    h = np.array([88.21, 46.32, 68.49, 46.72, 52.13, 70.23, 16.54])
    qf, qr = 120.0, 60.0
    T = steady_state(coarse_fe, h, ambient_c=23.2, q_front_w=qf, q_rear_w=qr)
    out = sum(
        hi * (zi @ T - 23.2 * ai)
        for hi, zi, ai in zip(h, coarse_fe.z_zone, coarse_fe.zone_area_m2, strict=True)
    )
    assert out == pytest.approx(qf + qr, rel=1e-9)
    assert np.abs(coarse_fe.K0 @ np.ones(coarse_fe.n_nodes)).max() < 1e-9  # conduction conserves energy
    assert coarse_fe.q_front.sum() == pytest.approx(1.0) and coarse_fe.q_rear.sum() == pytest.approx(1.0)


def test_affine_assembly_equals_direct_robin_assembly(coarse_fe) -> None:  # type: ignore[no-untyped-def]
    h = np.array([11.0, 22.0, 33.0, 44.0, 55.0, 66.0, 77.0])
    mesh = MeshTri(coarse_fe.nodes_rz.T.copy(), coarse_fe.triangles.T.copy())
    facets = np.concatenate(coarse_fe.zone_facets)
    h_facet = np.concatenate([np.full(f.size, hi) for f, hi in zip(coarse_fe.zone_facets, h, strict=True)])
    fb = FacetBasis(mesh, ElementTriP1(), facets=facets, intorder=3)

    @BilinearForm
    def robin(u, v, w):  # type: ignore[no-untyped-def]
        return w.h * u * v * 2 * np.pi * w.x[0]

    direct = coarse_fe.K0 + robin.assemble(fb, h=np.repeat(h_facet[:, None], fb.X.shape[1], axis=1))
    assert abs(stiffness(coarse_fe, h) - direct).max() < 1e-12 * abs(direct).max()
    z_direct = load_vector(coarse_fe, h, ambient_c=1.0, q_front_w=0.0, q_rear_w=0.0)
    assert np.allclose(
        z_direct, direct @ np.ones(coarse_fe.n_nodes) - coarse_fe.K0 @ np.ones(coarse_fe.n_nodes)
    )


def test_backward_euler_is_monotone_where_crank_nicolson_rings(coarse_fe) -> None:  # type: ignore[no-untyped-def]
    """The reason BE is the default: on a heat step with a large dt, CN's stiff modes oscillate."""
    h = np.full(7, 40.0)
    steady = coarse_fe.sensors(steady_state(coarse_fe, h, ambient_c=20.0, q_front_w=80.0, q_rear_w=40.0))
    big = InputSeries.constant(200, dt_s=600.0, ambient_c=20.0, q_front_w=80.0, q_rear_w=40.0)
    be, last = simulate_sensors(coarse_fe, h, big, 20.0, theta=1.0)
    cn, _ = simulate_sensors(coarse_fe, h, big, 20.0, theta=0.5)
    assert last.shape == (coarse_fe.n_nodes,)
    assert np.abs(be[-1] - steady).max() < 1e-8
    assert np.all(np.diff(be[:, 0]) >= 0)  # heating only: monotone rise
    assert np.any(np.diff(cn[:, 0]) < 0)  # CN overshoots and rings


def test_crank_nicolson_is_second_order_in_time(coarse_fe) -> None:  # type: ignore[no-untyped-def]
    h = np.full(7, 40.0)

    def at_1200s(dt: float, theta: float) -> np.ndarray:
        n = round(1200 / dt)
        inputs = InputSeries.constant(n, dt_s=dt, ambient_c=20.0, q_front_w=100.0, q_rear_w=50.0)
        return simulate_sensors(coarse_fe, h, inputs, 20.0, theta=theta)[0][-1]

    ref = at_1200s(1.25, 0.5)
    # CN needs a few steps to get past the start-up of a step load (order reduction), so smaller dt there.
    for theta, order, dt in ((1.0, 1.0, 40.0), (0.5, 2.0, 10.0)):
        e1 = np.abs(at_1200s(dt, theta) - ref).max()
        e2 = np.abs(at_1200s(dt / 2, theta) - ref).max()
        assert np.log2(e1 / e2) == pytest.approx(order, abs=0.3)


def test_bad_arguments_name_the_field(coarse_fe) -> None:  # type: ignore[no-untyped-def]
    inputs = InputSeries.constant(3, dt_s=10.0, ambient_c=20.0, q_front_w=1.0, q_rear_w=1.0)
    with pytest.raises(FEError, match=r"^h:"):
        simulate(coarse_fe, np.ones(6), inputs, 20.0)
    with pytest.raises(FEError, match=r"^h: must be >= 0"):
        simulate(coarse_fe, -np.ones(7), inputs, 20.0)
    with pytest.raises(FEError, match=r"^t0:"):
        simulate(coarse_fe, np.ones(7), inputs, np.zeros(5))
    with pytest.raises(FEError, match=r"^theta:"):
        simulate(coarse_fe, np.ones(7), inputs, 20.0, theta=0.2)


def test_banded_solver_matches_a_sparse_direct_solve(coarse_fe) -> None:  # type: ignore[no-untyped-def]
    h = np.array([88.21, 46.32, 68.49, 46.72, 52.13, 70.23, 16.54])
    K = stiffness(coarse_fe, h)
    Z = load_vector(coarse_fe, h, ambient_c=21.0, q_front_w=150.0, q_rear_w=70.0)
    direct = spsolve(K.tocsc(), Z)
    assert (
        np.abs(steady_state(coarse_fe, h, ambient_c=21.0, q_front_w=150.0, q_rear_w=70.0) - direct).max()
        < 1e-9
    )
    with pytest.raises(FEError, match=r"^h: at least one H must be > 0"):
        steady_state(coarse_fe, np.zeros(7), ambient_c=21.0, q_front_w=1.0, q_rear_w=1.0)
