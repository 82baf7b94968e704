"""The spindle's section deformed by the live field: what the dashboard draws exaggerated (pure, no I/O).

The displacement is linear in the temperature rise, u = K⁻¹ B ΔT (``model.thermoelastic``), and the live
field is the filtered state's reduced mean, T = Φ a (``service.estimate.state``). So the displacement of the
drawn nodes is a linear map of a, precomputed once per model (r sparse solves with one factorisation)::

    u = U_Φ a − T_ref · u_1          U_Φ = K⁻¹ B Φ,   u_1 = K⁻¹ B 1 (a uniform 1 K rise)

restricted to the nodes of the section's outline: the boundary of every region (shaft, housing, caps,
bearings, ...) on the *mechanical* mesh, whose floating bearing has its own nodes on the sliding surface (so
the drawing shows the slip there). A new field then costs one (2M × r) matrix-vector product (M outline
nodes), about 0.1 ms.

``build_section(growth, element_region, basis)`` once; ``section_displacement_um(op, state=a, t_ref_c=...)``
per view. Errors: ``GrowthEstimateError`` naming the bad input.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from model.thermoelastic import GrowthModel
from service.estimate.growth import GrowthEstimateError

__all__ = ["SectionOperator", "build_section", "section_displacement_um", "section_outline"]

Array = NDArray[np.float64]
M_TO_UM = 1e6


@dataclass(frozen=True, eq=False, kw_only=True)
class SectionOperator:
    """``nodes_rz`` (M, 2) [m] of the outline, ``edges`` (E, 2) indices into them; ``u_phi`` (2, M, r)
    [µm per unit reduced coordinate] and ``u_one`` (2, M) [µm/K] give (u_r, u_z) of those nodes."""

    nodes_rz: Array
    edges: NDArray[np.int64]
    u_phi: Array
    u_one: Array

    @property
    def rank(self) -> int:
        return int(self.u_phi.shape[2])


def section_outline(
    triangles: NDArray[np.int64], element_region: NDArray[np.int64]
) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """The edges (E, 2) of mesh node ids on the boundary of some region (the mesh boundary, or between two
    elements of different regions), and the sorted node ids they use (M,). ``triangles`` (n_el, 3)."""
    tri = np.asarray(triangles, dtype=np.int64)
    reg = np.asarray(element_region, dtype=np.int64)
    if tri.ndim != 2 or tri.shape[1] != 3 or reg.shape != (tri.shape[0],):
        raise GrowthEstimateError(
            f"element_region: expected one region per triangle ({tri.shape[0]}), got shape {reg.shape}"
        )
    e = np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]])
    e.sort(axis=1)
    owner = np.tile(reg, 3)
    keys, inverse, counts = np.unique(e, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.ravel()
    lo = np.full(len(keys), np.iinfo(np.int64).max)
    hi = np.full(len(keys), np.iinfo(np.int64).min)
    np.minimum.at(lo, inverse, owner)
    np.maximum.at(hi, inverse, owner)
    edges = keys[(counts == 1) | (lo != hi)]
    return edges, np.unique(edges)


def build_section(growth: GrowthModel, element_region: ArrayLike, basis: ArrayLike) -> SectionOperator:
    """The outline and its displacement operators (once per model: r + 1 solves with the factorised K).

    ``element_region`` (n_el,): the thermal mesh's (``FEModel.element_region``; the mechanical mesh has the
    same elements); ``basis`` Φ (N, r): the reduced model's, whose coordinates the live state's mean is."""
    solver = growth.solver
    phi = np.asarray(basis, dtype=float)
    if phi.ndim != 2 or phi.shape[0] != growth.n_nodes:
        raise GrowthEstimateError(f"basis: expected shape ({growth.n_nodes}, r), got {phi.shape}")
    mesh = solver.system.mesh
    edges, used = section_outline(np.asarray(mesh.t).T, np.asarray(element_region))
    cols = np.column_stack([phi, np.ones(growth.n_nodes)])  # the basis and a uniform 1 K rise
    f = solver.system.B @ cols[solver.expand]
    u = solver.T @ solver.lu.solve(np.asarray(solver.T.T @ f))  # (2Nm, r + 1) [m]
    dofs = solver.system.dofs[:, used]  # (2, M)
    per = M_TO_UM * u[dofs]  # (2, M, r + 1)
    remap = np.full(mesh.p.shape[1], -1, dtype=np.int64)
    remap[used] = np.arange(used.size)
    return SectionOperator(
        nodes_rz=np.asarray(mesh.p[:, used].T, dtype=float),
        edges=remap[edges],
        u_phi=np.ascontiguousarray(per[:, :, :-1]),
        u_one=np.ascontiguousarray(per[:, :, -1]),
    )


def section_displacement_um(op: SectionOperator, *, state: ArrayLike, t_ref_c: float) -> Array:
    """(u_r, u_z) (2, M) [µm] of the outline for the field Φ a over a uniform reference ``t_ref_c`` [°C]."""
    a = np.asarray(state, dtype=float)
    if a.shape != (op.rank,) or not np.all(np.isfinite(a)):
        raise GrowthEstimateError(f"state: expected {op.rank} finite reduced coordinates, got {a.shape}")
    if not np.isfinite(t_ref_c):
        raise GrowthEstimateError(f"t_ref_c: must be finite, got {t_ref_c}")
    return np.asarray(op.u_phi @ a - float(t_ref_c) * op.u_one)
