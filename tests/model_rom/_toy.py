"""A small stand-in affine system (axisymmetric P1 on an annular cylinder, 7 boundary zones, 32 sensors).

It has the same structure as ``model.fem.FEModel`` (E, K0, K_zone, z_zone, q_front, q_rear, sensor_op), so the
reduced model can be tested without the full spindle geometry.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.sparse as sp
from skfem import Basis, BilinearForm, ElementTriP1, FacetBasis, LinearForm, MeshTri
from skfem.helpers import dot, grad

R_IN, R_OUT, LENGTH = 0.02, 0.08, 0.30  # m
RHO_C = 3.6e6  # J/(m³·K), steel
CONDUCTIVITY = 45.0  # W/(m·K)


@dataclass(frozen=True)
class ToySpec:
    """What the ROM reads from a spec: the H box."""

    name: str = "toy"
    h_box: tuple[float, float] = (5.0, 200.0)


@dataclass(frozen=True)
class ToyFE:
    E: Any
    K0: Any
    K_zone: tuple[Any, ...]
    z_zone: np.ndarray
    q_front: np.ndarray
    q_rear: np.ndarray
    sensor_op: Any
    nodes_rz: np.ndarray
    triangles: np.ndarray

    @property
    def n_nodes(self) -> int:
        return int(self.nodes_rz.shape[0])


def _zone_of_facet(r: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Zone 0..6 of boundary facets by midpoint: outer surface in 4 parts, inner in 1, two end faces."""
    zone = np.full(r.shape, -1)
    tol = 1e-9
    outer = np.abs(r - R_OUT) < tol
    zone[outer] = np.minimum((z[outer] / LENGTH * 4).astype(int), 3)
    zone[np.abs(r - R_IN) < tol] = 4
    zone[(np.abs(z) < tol) & (zone < 0)] = 5
    zone[(np.abs(z - LENGTH) < tol) & (zone < 0)] = 6
    return zone


def build_toy(refine: int = 2) -> ToyFE:
    """Assemble the stand-in on a structured mesh (refine=2: 9x33 nodes; refine=3 about 1k nodes)."""
    mesh = MeshTri.init_tensor(
        np.linspace(R_IN, R_OUT, 2 + 2**refine), np.linspace(0.0, LENGTH, 2 + 8 * 2**refine)
    )
    basis = Basis(mesh, ElementTriP1())

    @BilinearForm
    def mass(u, v, w):  # type: ignore[no-untyped-def]
        return RHO_C * u * v * 2 * np.pi * w.x[0]

    @BilinearForm
    def stiff(u, v, w):  # type: ignore[no-untyped-def]
        return CONDUCTIVITY * dot(grad(u), grad(v)) * 2 * np.pi * w.x[0]

    @BilinearForm
    def robin(u, v, w):  # type: ignore[no-untyped-def]
        return u * v * 2 * np.pi * w.x[0]

    @LinearForm
    def unit(v, w):  # type: ignore[no-untyped-def]
        return v * 2 * np.pi * w.x[0]

    mid = mesh.p[:, mesh.facets[:, mesh.boundary_facets()]].mean(axis=1)
    zones = _zone_of_facet(mid[0], mid[1])
    k_zone, z_zone = [], []
    for i in range(7):
        fb = FacetBasis(mesh, ElementTriP1(), facets=mesh.boundary_facets()[zones == i])
        k_zone.append(robin.assemble(fb).tocsr())
        z_zone.append(unit.assemble(fb))
    q = []
    for z_lo, z_hi in ((0.02, 0.06), (0.22, 0.27)):
        elems = np.flatnonzero(
            (mesh.p[1, mesh.t].mean(axis=0) > z_lo) & (mesh.p[1, mesh.t].mean(axis=0) < z_hi)
        )
        sub = Basis(mesh, ElementTriP1(), elements=elems)
        load = unit.assemble(sub)
        q.append(load / load.sum())  # 1 W spread evenly over the bearing volume
    rng = np.random.default_rng(7)
    pts = np.vstack([rng.uniform(R_IN, R_OUT, 32), rng.uniform(0.0, LENGTH, 32)])
    return ToyFE(
        E=mass.assemble(basis).tocsr(),
        K0=stiff.assemble(basis).tocsr(),
        K_zone=tuple(k_zone),
        z_zone=np.array(z_zone),
        q_front=q[0],
        q_rear=q[1],
        sensor_op=sp.csr_matrix(basis.probes(pts)),
        nodes_rz=mesh.p.T.copy(),
        triangles=mesh.t.T.copy(),
    )
