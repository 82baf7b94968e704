"""Exact checks of the thermoelastic model: free expansion, two-material bars, adjoint = forward solve."""

from __future__ import annotations

import numpy as np
import pytest

from model.fem import FEModel, build_fe_model
from model.geometry import Region, SpindleSpec, spec_from_dict
from model.mesh import rect_mesh
from model.thermoelastic import (
    ElasticProperties,
    GrowthModel,
    ThermoelasticError,
    assemble_elasticity,
    build_growth_model,
    make_solver,
)
from tests.model_growth.conftest import packaged_doc

ALPHA = 11.5e-6
DT = 12.5  # K


def _uniform_alpha_spec() -> SpindleSpec:
    doc = packaged_doc()
    for m in doc["materials"].values():
        m["alpha_per_k"] = ALPHA  # E and nu stay different per material: a stress-free state must not care
    return spec_from_dict(doc)


@pytest.fixture(scope="module")
def uniform() -> tuple[SpindleSpec, FEModel, GrowthModel]:
    spec = _uniform_alpha_spec()
    fe = build_fe_model(spec, mesh_size_m=0.005)
    return spec, fe, build_growth_model(spec, fe)


def _rel(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.max(np.abs(a - b)) / np.max(np.abs(b)))


def test_uniform_rise_gives_alpha_l_dt_at_every_output(uniform) -> None:
    spec, fe, gm = uniform
    z_mount = spec.mechanics.mount.segments[0].z0_m
    got = gm.growth_um(np.full(fe.n_nodes, 20.0 + DT), 20.0)
    want = np.array(
        [
            ALPHA * DT * (z - z_mount if c == "axial" else r) * 1e6
            for (r, z), c in zip(gm.points_rz, gm.components, strict=True)
        ]
    )
    nonzero = np.abs(want) > 0
    assert np.all(np.abs(got[nonzero] - want[nonzero]) <= 1e-9 * np.abs(want[nonzero]))
    assert np.all(np.abs(got[~nonzero]) <= 1e-9 * np.max(np.abs(want)))
    assert gm.as_dict(got)["nose_axial"] == pytest.approx(ALPHA * DT * 0.060 * 1e6, rel=1e-9)


def test_uniform_rise_full_field_is_free_expansion(uniform) -> None:
    spec, fe, gm = uniform
    z_mount = spec.mechanics.mount.segments[0].z0_m
    u = gm.displacement_m(np.full(fe.n_nodes, DT), np.zeros(fe.n_nodes))
    p = gm.solver.system.mesh.p
    want = ALPHA * DT * np.column_stack([p[0], p[1] - z_mount])
    assert _rel(u, want) < 1e-9


def test_uniform_rise_does_not_depend_on_stiffness(uniform) -> None:
    _, fe, gm = uniform
    doc = packaged_doc()
    for m in doc["materials"].values():
        m["alpha_per_k"] = ALPHA
        m["e_pa"] *= 3.0
    gm3 = build_growth_model(spec_from_dict(doc), fe)
    rise = np.full(fe.n_nodes, DT)
    assert _rel(gm3.growth_um(rise, 0.0), gm.growth_um(rise, 0.0)) < 1e-9


def _bar(
    lengths: tuple[float, float], radius: float, size: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    z1 = lengths[0]
    regions = [
        Region("a", "a", 0.0, radius, 0.0, z1),
        Region("b", "b", 0.0, radius, z1, z1 + lengths[1]),
    ]
    m = rect_mesh(regions, size)
    return m.p, m.t, m.region


MATS = {"a": (2.1e11, 0.29, 11.5e-6), "b": (7.0e10, 0.33, 23.0e-6)}  # steel / aluminium


def _props(region: np.ndarray) -> ElasticProperties:
    table = np.array([MATS["a"], MATS["b"]])[region]
    return ElasticProperties(table[:, 0], table[:, 1], table[:, 2])


def _constrained(e: float, nu: float) -> float:
    return e * (1 - nu) / ((1 + nu) * (1 - 2 * nu))  # lambda + 2 mu


def _beta(e: float, nu: float, a: float) -> float:
    return e * a / (1 - 2 * nu)  # (3 lambda + 2 mu) alpha


def test_two_material_bar_free_end_laterally_confined() -> None:
    (l1, l2), dt = (0.12, 0.07), 8.0
    p, t, reg = _bar((l1, l2), 0.02, 0.004)
    system = assemble_elasticity(p, t, _props(reg))
    base = system.dofs[1, np.abs(p[1]) < 1e-12]
    solver = make_solver(system, fixed=np.concatenate([system.dofs[0], base]))
    u = solver.displacement(np.full(p.shape[1], dt))
    # uniaxial strain: sigma_zz = 0, eps_zz = (1 + nu)/(1 - nu) alpha dT in each material
    strain = {k: (1 + nu) / (1 - nu) * a * dt for k, (_, nu, a) in MATS.items()}
    want = np.where(p[1] <= l1, strain["a"] * p[1], strain["a"] * l1 + strain["b"] * (p[1] - l1))
    assert _rel(u[:, 1], want) < 1e-9
    assert np.max(np.abs(u[:, 0])) == 0.0


def test_two_material_bar_between_rigid_walls_laterally_confined() -> None:
    (l1, l2), dt = (0.09, 0.15), -6.0
    p, t, reg = _bar((l1, l2), 0.03, 0.005)
    system = assemble_elasticity(p, t, _props(reg))
    ends = np.abs(p[1]) < 1e-12
    ends |= np.abs(p[1] - (l1 + l2)) < 1e-12
    solver = make_solver(system, fixed=np.concatenate([system.dofs[0], system.dofs[1, ends]]))
    u = solver.displacement(np.full(p.shape[1], dt))
    m = {k: _constrained(e, nu) for k, (e, nu, _) in MATS.items()}
    b = {k: _beta(e, nu, a) for k, (e, nu, a) in MATS.items()}
    # one axial stress s in both: eps_i = (s + b_i dT)/m_i, eps_a l1 + eps_b l2 = 0
    s = -(b["a"] * dt * l1 / m["a"] + b["b"] * dt * l2 / m["b"]) / (l1 / m["a"] + l2 / m["b"])
    ea, eb = (s + b["a"] * dt) / m["a"], (s + b["b"] * dt) / m["b"]
    want = np.where(p[1] <= l1, ea * p[1], ea * l1 + eb * (p[1] - l1))
    assert _rel(u[:, 1], want) < 1e-9
    assert abs(ea * l1) > 1e-6  # the interface really moves (aluminium pushes the steel)


def test_operator_equals_forward_solve(fe: FEModel, growth: GrowthModel) -> None:
    rng = np.random.default_rng(3)
    r, z = fe.nodes_rz.T
    field = 20 + 8 * np.exp(-(((z - 0.5) / 0.1) ** 2)) + 3 * r / 0.1 + rng.normal(0, 0.5, fe.n_nodes)
    u = growth.displacement_m(field, 20.0)
    p = growth.solver.system.mesh.p
    for k, ((pr, pz), comp) in enumerate(zip(growth.points_rz, growth.components, strict=True)):
        node = int(np.argmin((p[0] - pr) ** 2 + (p[1] - pz) ** 2))
        want = u[node, 1 if comp == "axial" else 0] * 1e6
        assert growth.growth_um(field, 20.0)[k] == pytest.approx(want, rel=1e-9, abs=1e-12)


def test_reduced_operator_is_g_phi(fe: FEModel, growth: GrowthModel) -> None:
    rng = np.random.default_rng(4)
    phi = rng.normal(size=(fe.n_nodes, 6))
    a = rng.normal(size=6)
    assert np.allclose(growth.reduced(phi) @ a, growth.growth_um(phi @ a, 0.0), rtol=1e-12, atol=1e-12)


def test_floating_bearing_slides_axially_and_stays_in_radial_contact(
    fe: FEModel, growth: GrowthModel
) -> None:
    r = fe.nodes_rz[:, 0]
    field = 20 + 15 * (r < 0.0401)  # hot shaft, cold housing: the shaft must slide in the rear bearing
    u = growth.displacement_m(field, 20.0)
    n = fe.n_nodes
    dup = np.arange(n, u.shape[0])
    orig = growth.solver.expand[dup]
    assert dup.size >= 2
    assert np.allclose(u[dup, 0], u[orig, 0], rtol=0, atol=1e-15)
    assert np.max(np.abs(u[dup, 1] - u[orig, 1])) > 1e-6  # more than a micrometre of slip


def test_body_not_held_axially_is_refused() -> None:
    p, t, reg = _bar((0.05, 0.05), 0.02, 0.01)
    system = assemble_elasticity(p, t, _props(reg))
    axis = system.dofs[0, np.abs(p[0]) < 1e-12]
    with pytest.raises(ThermoelasticError, match="held axially"):
        make_solver(system, fixed=axis)  # only the axis: free to translate along z


def test_mount_held_radially_when_asked(fe: FEModel) -> None:
    doc = packaged_doc()
    doc["mechanics"]["mount"]["fix"] = "axial_radial"
    gm = build_growth_model(spec_from_dict(doc), fe)
    u = gm.displacement_m(np.full(fe.n_nodes, 30.0), 20.0)
    p = gm.solver.system.mesh.p
    on_mount = (np.abs(p[1] - 0.550) < 1e-9) & (p[0] > 0.080 - 1e-9)
    assert on_mount.sum() >= 2
    assert np.all(u[on_mount] == 0.0)
    assert np.max(np.abs(u)) > 1e-5  # the rest still grows


def test_wrong_shapes_name_the_argument(fe: FEModel, growth: GrowthModel) -> None:
    with pytest.raises(ThermoelasticError, match="field_c"):
        growth.growth_um(np.zeros(fe.n_nodes + 1), 20.0)
    with pytest.raises(ThermoelasticError, match="t_ref_c"):
        growth.growth_um(np.zeros(fe.n_nodes), np.zeros(3))
    with pytest.raises(ThermoelasticError, match="phi"):
        growth.reduced(np.zeros((fe.n_nodes - 1, 2)))
    with pytest.raises(ThermoelasticError, match="name"):
        growth.operator("tool_tip")
