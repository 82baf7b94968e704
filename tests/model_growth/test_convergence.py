"""Mesh convergence: a shrink-fit-like composite cylinder against Lamé, and the spindle's outputs."""

from __future__ import annotations

import numpy as np
import pytest

from benchmarks.studies.growth_check import mesh_study
from model.geometry import Region, SpindleSpec
from model.mesh import rect_mesh
from model.thermoelastic import ElasticProperties, assemble_elasticity, make_solver

CORE = (2.1e11, 0.29, 11.5e-6)  # steel core 0..a
SLEEVE = (7.0e10, 0.33, 23.0e-6)  # aluminium sleeve a..b
A, B, L, DT = 0.03, 0.05, 0.02, 10.0


def _lame(r: np.ndarray) -> np.ndarray:
    """Plane strain (u_z = 0), uniform dT: core u = c1 r, sleeve u = c2 r + c3 / r, free outer surface."""

    def lm(e: float, nu: float, a: float) -> tuple[float, float, float]:
        return e * nu / ((1 + nu) * (1 - 2 * nu)), e / (2 * (1 + nu)), e * a / (1 - 2 * nu)

    l1, m1, b1 = lm(*CORE)
    l2, m2, b2 = lm(*SLEEVE)
    # sigma_rr of u = c r + d / r: 2 (lam + mu) c - 2 mu d / r^2 - beta dT
    mat = np.array(
        [
            [A, -A, -1 / A],  # u continuous at a
            [2 * (l1 + m1), -2 * (l2 + m2), 2 * m2 / A**2],  # sigma_rr continuous at a
            [0.0, 2 * (l2 + m2), -2 * m2 / B**2],  # sigma_rr(b) = 0
        ]
    )
    c1, c2, c3 = np.linalg.solve(mat, [0.0, (b1 - b2) * DT, b2 * DT])
    return np.where(r <= A, c1 * r, c2 * r + c3 / np.maximum(r, 1e-30))


def _composite_error(size: float) -> float:
    m = rect_mesh([Region("core", "c", 0, A, 0, L), Region("sleeve", "s", A, B, 0, L)], size)
    table = np.array([CORE, SLEEVE])[m.region]
    system = assemble_elasticity(m.p, m.t, ElasticProperties(table[:, 0], table[:, 1], table[:, 2]))
    axis = system.dofs[0, m.p[0] < 1e-12]
    ends = system.dofs[1, (m.p[1] < 1e-12) | (m.p[1] > L - 1e-12)]  # rollers: plane strain
    u = make_solver(system, fixed=np.concatenate([axis, ends])).displacement(np.full(m.p.shape[1], DT))
    exact = _lame(m.p[0])
    return float(np.max(np.abs(u[:, 0] - exact)) / np.max(np.abs(exact)))


def test_composite_cylinder_converges_at_second_order() -> None:
    sizes = (0.004, 0.002, 0.001)
    errs = [_composite_error(s) for s in sizes]
    rates = np.log2(np.array(errs[:-1]) / np.array(errs[1:]))
    # observed: max nodal error 1.3e-3, 3.9e-4, 1.1e-4, rates 1.72, 1.78 (P1 max-norm: O(h^2 log 1/h))
    assert errs[-1] < 2e-4
    assert np.all(rates > 1.65), (errs, rates)
    assert rates[1] > rates[0]


@pytest.mark.slow
def test_spindle_outputs_converge_to_one_percent(spec: SpindleSpec) -> None:
    rows = mesh_study(spec, sizes_m=(0.005, 0.0025), reference_m=0.00125, speed_rpm=5000.0)
    coarse, default = rows
    for name in ("nose_axial", "nose_radial", "housing_axial"):
        assert abs(default.rel_err[name]) < 0.01, (name, default.rel_err)
        assert abs(default.rel_err[name]) < abs(coarse.rel_err[name]) + 1e-4, (name, coarse, default)
