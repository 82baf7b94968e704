"""Axisymmetric P1 finite-element thermal model of the spindle, assembled once, affine in H.

Weak form (weight 2 pi r in every integral)::

    E dT/dt + K(H) T = Z(H, Ti, Q)
    K(H) = K0 + sum_i H_i K_i                  K_i = int_{Gamma_i} u v 2 pi r ds
    Z    = s_f Q_f q_front + s_r Q_r q_rear + Ti sum_i H_i z_i,   z_i = int_{Gamma_i} v 2 pi r ds

Boundaries that belong to no zone (and the axis r = 0) are adiabatic. ``q_front``/``q_rear`` are the bearing
heat loads per watt, spread uniformly over the volume of the bearing regions (each sums to 1 W).

Time stepping is the theta-method with inputs held constant over each step (``InputSeries`` entry k applies on
step k -> k+1), so (1-theta) Z(n) + theta Z(n+1) = Z_k::

    (E/dt + theta K) T(n+1) = (E/dt - (1-theta) K) T(n) + Z_k

The system matrix is factorised once per (H, dt, theta) (banded Cholesky, ``model.banded``) and reused for
every step.

Errors::

    FEError(ValueError)   zone without facets, overlapping zones, sensor outside the mesh, bad H/t0 shape
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from numpy.typing import ArrayLike, NDArray
from skfem import Basis, BilinearForm, ElementTriP1, FacetBasis, Functional, LinearForm, MeshTri
from skfem.helpers import dot, grad

from model.banded import BandedCholesky, SolverError, band_order
from model.errors import ModelError
from model.geometry import N_CHANNELS, SpindleSpec, ZoneSpec
from model.inputs import InputSeries
from model.mesh import rect_mesh

TWO_PI = 2.0 * np.pi
_TOL = 1e-9


class FEError(ModelError, ValueError):
    """The FE model cannot be built or evaluated; the message names the field."""


@BilinearForm
def _capacity(u, v, w):  # type: ignore[no-untyped-def]
    return w.rho_c * u * v * TWO_PI * w.x[0]


@BilinearForm
def _conduction(u, v, w):  # type: ignore[no-untyped-def]
    return w.k * dot(grad(u), grad(v)) * TWO_PI * w.x[0]


@BilinearForm
def _robin(u, v, w):  # type: ignore[no-untyped-def]
    return u * v * TWO_PI * w.x[0]


@LinearForm
def _robin_rhs(v, w):  # type: ignore[no-untyped-def]
    return v * TWO_PI * w.x[0]


@LinearForm
def _volume_load(v, w):  # type: ignore[no-untyped-def]
    return w.ind * v * TWO_PI * w.x[0]


@Functional
def _area(w):  # type: ignore[no-untyped-def]
    return TWO_PI * w.x[0]


@dataclass(frozen=True, eq=False)
class FEModel:
    """Assembled FE model. Matrices are scipy CSR; fields are nodal values (N,)."""

    nodes_rz: NDArray[np.float64]  # (N, 2) [m]
    triangles: NDArray[np.int64]  # (M, 3)
    element_region: NDArray[np.int64]  # (M,) index into spec.regions
    E: sp.csr_matrix  # capacity [J/K]
    K0: sp.csr_matrix  # conduction [W/K]
    K_zone: tuple[sp.csr_matrix, ...]  # 7 boundary mass matrices [m^2]
    z_zone: NDArray[np.float64]  # (7, N) boundary load vectors [m^2]
    q_front: NDArray[np.float64]  # (N,) per watt of front bearing heat
    q_rear: NDArray[np.float64]  # (N,)
    sensor_op: sp.csr_matrix  # (32, N) interpolation
    zone_area_m2: NDArray[np.float64]  # (7,)
    mesh_size_m: float
    zone_facets: tuple[NDArray[np.int64], ...] = field(default=())
    adiabatic_area_m2: float = 0.0

    @property
    def n_nodes(self) -> int:
        """Number of nodes N."""
        return int(self.nodes_rz.shape[0])

    def sensors(self, fields: NDArray[np.float64]) -> NDArray[np.float64]:
        """Sensor temperatures [degC] from a field (N,) -> (32,) or a trajectory (n, N) -> (n, 32)."""
        return np.asarray((self.sensor_op @ np.asarray(fields).T).T)


# ---------------------------------------------------------------- assembly


def _element_values(basis: Basis, per_element: NDArray[np.float64]) -> NDArray[np.float64]:
    return np.repeat(per_element[:, None], basis.X.shape[1], axis=1)


def _segment_mask(
    mid: NDArray[np.float64], a: NDArray[np.float64], b: NDArray[np.float64], seg: object
) -> NDArray[np.bool_]:
    r0, z0, r1, z1 = (getattr(seg, f) for f in ("r0_m", "z0_m", "r1_m", "z1_m"))
    if r0 == r1:  # vertical segment r = const
        on_line = (np.abs(a[0] - r0) < _TOL) & (np.abs(b[0] - r0) < _TOL)
        inside = (mid[1] > min(z0, z1) - _TOL) & (mid[1] < max(z0, z1) + _TOL)
    else:
        on_line = (np.abs(a[1] - z0) < _TOL) & (np.abs(b[1] - z0) < _TOL)
        inside = (mid[0] > min(r0, r1) - _TOL) & (mid[0] < max(r0, r1) + _TOL)
    return np.asarray(on_line & inside)


def tag_zone_facets(
    mesh: MeshTri, zones: Sequence[ZoneSpec]
) -> tuple[tuple[NDArray[np.int64], ...], NDArray[np.int64]]:
    """Boundary facets of each zone, and the untagged boundary facets off the axis (adiabatic)."""
    bf = mesh.boundary_facets()
    a, b = mesh.p[:, mesh.facets[0, bf]], mesh.p[:, mesh.facets[1, bf]]
    mid = 0.5 * (a + b)
    owner = np.full(bf.size, -1)
    out = []
    for i, zone in enumerate(zones):
        mask = np.zeros(bf.size, dtype=bool)
        for seg in zone.segments:
            mask |= _segment_mask(mid, a, b, seg)
        clash = mask & (owner >= 0)
        if clash.any():
            other = zones[int(owner[clash][0])].name
            raise FEError(
                f"zones[{i}].segments: overlap zone {other} near (r, z) = {tuple(mid[:, clash][:, 0])}"
            )
        if not mask.any():
            raise FEError(f"zones[{i}].segments: no boundary facet of the mesh lies on them")
        owner[mask] = i
        out.append(bf[mask])
    on_axis = (np.abs(a[0]) < _TOL) & (np.abs(b[0]) < _TOL)
    return tuple(out), bf[(owner < 0) & ~on_axis]


def _heat_vector(basis: Basis, elem_mask: NDArray[np.bool_], what: str) -> NDArray[np.float64]:
    if not elem_mask.any():
        raise FEError(f"regions: no mesh element carries heat = {what!r}")
    vec = _volume_load.assemble(basis, ind=_element_values(basis, elem_mask.astype(float)))
    return np.asarray(vec / vec.sum())


def _sensor_operator(basis: Basis, spec: SpindleSpec) -> sp.csr_matrix:
    pts = np.array([[s.r_m for s in spec.sensors], [s.z_m for s in spec.sensors]])
    try:
        op = sp.csr_matrix(basis.probes(pts))
    except ValueError as err:
        raise FEError(f"sensors: a sensor lies outside the mesh ({err})") from err
    if op.shape != (N_CHANNELS, basis.N):
        raise FEError(f"sensors: expected {N_CHANNELS} channels")
    return op


def build_fe_model(spec: SpindleSpec, *, mesh_size_m: float | None = None, align: bool = True) -> FEModel:
    """Mesh and assemble the spindle once; ``mesh_size_m`` None uses ``spec.default_mesh_size_m`` [m].

    ``align`` draws grid lines through the sensors where possible, so they sit on nodes.
    """
    size = spec.default_mesh_size_m if mesh_size_m is None else float(mesh_size_m)
    ends = [(x.r0_m, x.z0_m) for z in spec.zones for x in z.segments]
    ends += [(x.r1_m, x.z1_m) for z in spec.zones for x in z.segments]
    points = [(s.r_m, s.z_m) for s in spec.sensors] if align else []
    rm = rect_mesh(spec.regions, size, points_rz=points, edges_rz=ends)
    mesh = MeshTri(rm.p, rm.t)
    basis = Basis(mesh, ElementTriP1(), intorder=3)
    mats = [spec.materials[g.material] for g in spec.regions]
    k_el = np.array([mats[i].k_w_mk for i in rm.region])
    rc_el = np.array([mats[i].rho_kg_m3 * mats[i].c_j_kgk for i in rm.region])
    E = _capacity.assemble(basis, rho_c=_element_values(basis, rc_el)).tocsr()
    K0 = _conduction.assemble(basis, k=_element_values(basis, k_el)).tocsr()
    facets, adiabatic = tag_zone_facets(mesh, spec.zones)
    K_zone, z_zone, area = [], [], []
    for f in facets:
        fb = FacetBasis(mesh, ElementTriP1(), facets=f, intorder=3)
        K_zone.append(_robin.assemble(fb).tocsr())
        z_zone.append(_robin_rhs.assemble(fb))
        area.append(_area.assemble(fb))
    adiabatic_area = (
        _area.assemble(FacetBasis(mesh, ElementTriP1(), facets=adiabatic)) if adiabatic.size else 0.0
    )
    heat = np.array([spec.regions[i].heat for i in rm.region])
    return FEModel(
        nodes_rz=mesh.p.T.copy(),
        triangles=mesh.t.T.astype(np.int64),
        element_region=rm.region,
        E=E,
        K0=K0,
        K_zone=tuple(K_zone),
        z_zone=np.array(z_zone),
        q_front=_heat_vector(basis, heat == "front", "front"),
        q_rear=_heat_vector(basis, heat == "rear", "rear"),
        sensor_op=_sensor_operator(basis, spec),
        zone_area_m2=np.array(area),
        mesh_size_m=size,
        zone_facets=facets,
        adiabatic_area_m2=float(adiabatic_area),
    )


# ---------------------------------------------------------------- operators


def _check_h(fe: FEModel, h: ArrayLike) -> NDArray[np.float64]:
    hv = np.asarray(h, dtype=float)
    if hv.shape != (len(fe.K_zone),) or not np.all(np.isfinite(hv)):
        raise FEError(f"h: expected {len(fe.K_zone)} finite values, got shape {hv.shape}")
    if np.any(hv < 0):
        raise FEError(f"h: must be >= 0, got {hv.tolist()}")
    return hv


def stiffness(fe: FEModel, h: ArrayLike) -> sp.csr_matrix:
    """K(H) = K0 + sum_i H_i K_i [W/K] for H [W/(m^2 K)]."""
    hv = _check_h(fe, h)
    K = fe.K0.copy()
    for hi, Ki in zip(hv, fe.K_zone, strict=True):
        K = K + hi * Ki
    return K.tocsr()


def robin_load(fe: FEModel, h: ArrayLike) -> NDArray[np.float64]:
    """sum_i H_i z_i [W/K]: multiply by Ti [degC] for the ambient part of Z."""
    return np.asarray(_check_h(fe, h) @ fe.z_zone)


def load_vector(
    fe: FEModel,
    h: ArrayLike,
    *,
    ambient_c: float,
    q_front_w: float,
    q_rear_w: float,
    load_scale: tuple[float, float] = (1.0, 1.0),
) -> NDArray[np.float64]:
    """Z = s_f Q_f q_front + s_r Q_r q_rear + Ti sum_i H_i z_i [W]."""
    return (
        load_scale[0] * q_front_w * fe.q_front
        + load_scale[1] * q_rear_w * fe.q_rear
        + ambient_c * robin_load(fe, h)
    )


def _initial(fe: FEModel, t0: float | ArrayLike) -> NDArray[np.float64]:
    a = np.asarray(t0, dtype=float)
    if a.ndim == 0:
        return np.full(fe.n_nodes, float(a))
    if a.shape != (fe.n_nodes,):
        raise FEError(f"t0: expected a scalar or shape ({fe.n_nodes},), got {a.shape}")
    return a.copy()


@dataclass(frozen=True, eq=False)
class Stepper:
    """The theta-method for one (H, dt, theta): A = E/dt + theta K factorised, B = E/dt - (1-theta) K."""

    fe: FEModel
    h: NDArray[np.float64]
    dt_s: float
    theta: float
    lu: BandedCholesky
    B: sp.csr_matrix
    zh: NDArray[np.float64]

    def load_terms(
        self, inputs: InputSeries, load_scale: tuple[float, float]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Z_k = coef[k] @ basis: coefficients (n_steps, 3) [W, W, degC] and basis vectors (3, N)."""
        coef = np.column_stack(
            [load_scale[0] * inputs.q_front_w, load_scale[1] * inputs.q_rear_w, inputs.ambient_c]
        )
        return coef, np.vstack([self.fe.q_front, self.fe.q_rear, self.zh])

    def march(
        self,
        inputs: InputSeries,
        t0: float | ArrayLike,
        *,
        load_scale: tuple[float, float] = (1.0, 1.0),
        keep_fields: bool = True,
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Advance from t0; return (fields (n+1, N) or final field (1, N), sensors (n+1, 32)) [degC]."""
        if abs(inputs.dt_s - self.dt_s) > 1e-12 * self.dt_s:
            raise FEError(f"inputs.dt_s: {inputs.dt_s} differs from the factorised dt {self.dt_s}")
        T = _initial(self.fe, t0)
        coef, basis = self.load_terms(inputs, load_scale)
        sens = np.empty((inputs.n_steps + 1, N_CHANNELS))
        sens[0] = self.fe.sensor_op @ T
        fields = np.empty((inputs.n_steps + 1, T.size)) if keep_fields else None
        if fields is not None:
            fields[0] = T
        solve = self.lu.solve
        for k in range(inputs.n_steps):
            T = solve(self.B @ T + coef[k] @ basis)
            sens[k + 1] = self.fe.sensor_op @ T
            if fields is not None:
                fields[k + 1] = T
        return (fields if fields is not None else T[None, :]), sens


def _factorise(fe: FEModel, A: sp.spmatrix) -> BandedCholesky:
    """Banded Cholesky of an SPD system matrix in the FE model's band order."""
    try:
        return BandedCholesky(A, band_order(fe.nodes_rz))
    except SolverError as err:
        raise FEError(f"h: system not positive definite ({err}); is every H zero?") from err


def make_stepper(fe: FEModel, h: ArrayLike, *, dt_s: float, theta: float = 1.0) -> Stepper:
    """Factorise the theta-method system for H [W/(m^2 K)], step dt_s [s] and theta in [0.5, 1]."""
    if not 0.5 <= theta <= 1.0:
        raise FEError(f"theta: must be in [0.5, 1] (unconditionally stable), got {theta!r}")
    if not dt_s > 0:
        raise FEError(f"dt_s: must be > 0, got {dt_s!r}")
    hv = _check_h(fe, h)
    K = stiffness(fe, hv)
    A = (fe.E / dt_s + theta * K).tocsr()
    B = (fe.E / dt_s - (1.0 - theta) * K).tocsr()
    return Stepper(fe, hv, float(dt_s), float(theta), _factorise(fe, A), B, robin_load(fe, hv))


def simulate(
    fe: FEModel,
    h: ArrayLike,
    inputs: InputSeries,
    t0: float | ArrayLike,
    *,
    theta: float = 1.0,
    load_scale: tuple[float, float] = (1.0, 1.0),
) -> NDArray[np.float64]:
    """Transient temperature fields (n_steps + 1, N) [degC] from t0 (scalar or (N,) field) under ``inputs``.

    theta = 1 (backward Euler, default: L-stable, no ringing on input steps) or 0.5 (Crank-Nicolson).
    ``load_scale`` multiplies the front/rear bearing heats (used when the loads are estimated).
    """
    fields, _ = make_stepper(fe, h, dt_s=inputs.dt_s, theta=theta).march(inputs, t0, load_scale=load_scale)
    return fields


def simulate_sensors(
    fe: FEModel,
    h: ArrayLike,
    inputs: InputSeries,
    t0: float | ArrayLike,
    *,
    theta: float = 1.0,
    load_scale: tuple[float, float] = (1.0, 1.0),
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Like ``simulate`` but keeps only the sensors: (sensors (n_steps + 1, 32), final field (N,)) [degC]."""
    stepper = make_stepper(fe, h, dt_s=inputs.dt_s, theta=theta)
    last, sens = stepper.march(inputs, t0, load_scale=load_scale, keep_fields=False)
    return sens, last[0]


def steady_state(
    fe: FEModel,
    h: ArrayLike,
    *,
    ambient_c: float,
    q_front_w: float,
    q_rear_w: float,
    load_scale: tuple[float, float] = (1.0, 1.0),
) -> NDArray[np.float64]:
    """Steady field (N,) [degC]: K(H) T = Z for constant ambient [degC] and bearing heats [W]."""
    if not np.any(_check_h(fe, h) > 0):
        raise FEError("h: at least one H must be > 0 for a steady state (else no heat leaves the spindle)")
    K = stiffness(fe, h)
    Z = load_vector(fe, h, ambient_c=ambient_c, q_front_w=q_front_w, q_rear_w=q_rear_w, load_scale=load_scale)
    return _factorise(fe, K).solve(Z)
