"""The deformed section (``service.estimate.growth_section``): its outline, and its reduced displacement
operator against a full forward solve of the same field."""

from __future__ import annotations

import numpy as np
import pytest

from model.fem import FEModel
from model.thermoelastic import GrowthModel
from service.estimate.growth import GrowthEstimateError
from service.estimate.growth_section import build_section, section_displacement_um, section_outline


def test_outline_is_the_mesh_boundary_and_every_region_boundary() -> None:
    # a unit square of two triangles, then a third triangle of another region on its right
    tri = np.array([[0, 1, 2], [0, 2, 3], [1, 4, 2]])
    edges, used = section_outline(tri[:2], np.array([0, 0]))
    assert {tuple(e) for e in edges} == {(0, 1), (1, 2), (2, 3), (0, 3)}  # not the diagonal (0, 2)
    edges, used = section_outline(tri, np.array([0, 0, 1]))
    assert {tuple(e) for e in edges} == {(0, 1), (1, 2), (2, 3), (0, 3), (1, 4), (2, 4)}
    assert used.tolist() == [0, 1, 2, 3, 4]
    same, _ = section_outline(tri, np.array([0, 0, 0]))
    assert (1, 2) not in {tuple(e) for e in same}  # inside one region: not drawn
    with pytest.raises(GrowthEstimateError, match="element_region"):
        section_outline(tri, np.array([0, 0]))


def test_reduced_operator_equals_a_forward_solve(fe: FEModel, growth: GrowthModel) -> None:
    rng = np.random.default_rng(3)
    basis = np.column_stack([np.ones(fe.n_nodes), fe.nodes_rz[:, 1], rng.normal(size=(fe.n_nodes, 3))])
    op = build_section(growth, fe.element_region, basis)
    a = np.array([24.0, 8.0, 0.3, -0.2, 0.5])
    u = section_displacement_um(op, state=a, t_ref_c=21.5)
    full = growth.displacement_m(basis @ a, 21.5) * 1e6  # (Nm, 2) on every mechanical node
    p = np.asarray(growth.solver.system.mesh.p).T
    _, used = section_outline(np.asarray(growth.solver.system.mesh.t).T, fe.element_region)
    np.testing.assert_allclose(op.nodes_rz, p[used], atol=0)
    np.testing.assert_allclose(u, full[used].T, atol=1e-9 * np.abs(full).max())
    # the floating rear bearing's sliding surface is drawn on both sides (its own nodes: the slip)
    assert len(used) > len(np.unique(np.round(p[used], 9), axis=0))
    with pytest.raises(GrowthEstimateError, match="state"):
        section_displacement_um(op, state=a[:3], t_ref_c=21.5)
    with pytest.raises(GrowthEstimateError, match="t_ref_c"):
        section_displacement_um(op, state=a, t_ref_c=float("nan"))
    with pytest.raises(GrowthEstimateError, match="basis"):
        build_section(growth, fe.element_region, basis[:10])
