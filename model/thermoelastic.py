"""Axisymmetric linear thermoelasticity of the spindle and its growth operators (linear in temperature).

On the thermal model's mesh (``FEModel.nodes_rz``/``triangles``), displacement u = (u_r, u_z) in P1 vector
elements; strains ε_rr = ∂u_r/∂r, ε_zz = ∂u_z/∂z, ε_θθ = u_r/r, γ_rz = ∂u_r/∂z + ∂u_z/∂r. Weak form (weight
2πr everywhere)::

    K u = B ΔT        K = ∫ [λ tr ε(u) tr ε(v) + 2μ (ε(u):ε(v))] 2πr,   B = ∫ β φ tr ε(v) 2πr,
                      β = E α / (1 − 2ν),   ΔT = T − T_ref (P1 nodal, the thermal model's field)

Boundary conditions (``[mechanics]`` in the spindle TOML, docs/design/growth.md): u_r = 0 on the axis; u_z = 0
(and u_r = 0 with ``fix = "axial_radial"``) on the housing's mounting face; the shaft is held axially only
through the bearings that are fused into the mesh (the locating front pair); a *floating* bearing gets its own
copy of the nodes on the sliding surface, tied to the other side in u_r only (frictionless axial slide).

Because u is linear in ΔT, each output (a displacement component at a point) is y = g·ΔT with
g = Pᵀ Bᵀ K⁻¹ c (one adjoint solve per output, done once); a new field then costs a dot product, and a reduced
basis Φ gives g·Φ. Operators are stored in µm/K.

Errors::

    ThermoelasticError(ValueError)   no [mechanics] section, a mount or floating surface the mesh does not
                                     have, a field of the wrong shape
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from numpy.typing import ArrayLike, NDArray
from skfem import Basis, BilinearForm, ElementTriP1, ElementVector, MeshTri
from skfem.helpers import grad

from model.errors import ModelError
from model.fem import FEModel
from model.geometry import MechanicsSpec, Segment2D, SpindleSpec

TWO_PI = 2.0 * np.pi
M_TO_UM = 1e6
_TOL = 1e-9
Array = NDArray[np.float64]


class ThermoelasticError(ModelError, ValueError):
    """The thermoelastic model cannot be built or evaluated; the message names the field."""


# ---------------------------------------------------------------- forms


def _strains(u, r):  # type: ignore[no-untyped-def]
    du = grad(u)
    return du[0, 0], du[1, 1], u[0] / r, du[0, 1] + du[1, 0]


@BilinearForm
def _stiffness(u, v, w):  # type: ignore[no-untyped-def]
    r = w.x[0]
    urr, uzz, utt, urz = _strains(u, r)
    vrr, vzz, vtt, vrz = _strains(v, r)
    tr_u, tr_v = urr + uzz + utt, vrr + vzz + vtt
    normal = urr * vrr + uzz * vzz + utt * vtt
    return (w.lam * tr_u * tr_v + 2.0 * w.mu * normal + w.mu * urz * vrz) * TWO_PI * r


@BilinearForm
def _thermal_load(t, v, w):  # type: ignore[no-untyped-def]
    r = w.x[0]
    vrr, vzz, vtt, _ = _strains(v, r)
    return w.beta * t * (vrr + vzz + vtt) * TWO_PI * r


# ---------------------------------------------------------------- assembly (pure, any mesh)


@dataclass(frozen=True)
class ElasticProperties:
    """Per-element E [Pa], ν [-], α [1/K], each (M,)."""

    e_pa: Array
    nu: Array
    alpha_per_k: Array


@dataclass(frozen=True, eq=False)
class ElasticSystem:
    """Assembled K (2Nm, 2Nm) [N/m] and B (2Nm, Nm) [N/K]; ``dofs`` (2, Nm): u_r and u_z dof of each node."""

    mesh: MeshTri
    K: sp.csr_matrix
    B: sp.csr_matrix
    dofs: NDArray[np.int64]


def _per_element(basis: Basis, values: Array) -> Array:
    return np.repeat(np.asarray(values, dtype=float)[:, None], basis.X.shape[1], axis=1)


def assemble_elasticity(p: Array, t: NDArray[np.int64], props: ElasticProperties) -> ElasticSystem:
    """Assemble K and B once on nodes ``p`` (2, Nm) [m] and triangles ``t`` (3, M), P1 vector elements."""
    mesh = MeshTri(np.asarray(p, dtype=float), np.asarray(t, dtype=np.int64))
    vbasis = Basis(mesh, ElementVector(ElementTriP1()), intorder=2)
    sbasis = Basis(mesh, ElementTriP1(), intorder=2)
    e, nu, alpha = props.e_pa, props.nu, props.alpha_per_k
    lam = e * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))
    mu = e / (2.0 * (1.0 + nu))
    beta = e * alpha / (1.0 - 2.0 * nu)
    K = _stiffness.assemble(vbasis, lam=_per_element(vbasis, lam), mu=_per_element(vbasis, mu))
    B = _thermal_load.assemble(sbasis, vbasis, beta=_per_element(vbasis, beta))
    return ElasticSystem(mesh, K.tocsr(), B.tocsr(), np.asarray(vbasis.nodal_dofs, dtype=np.int64))


def reduction(n_dof: int, fixed: ArrayLike, slaves: ArrayLike, masters: ArrayLike) -> sp.csr_matrix:
    """T (n_dof, n_free) with u = T a: ``fixed`` dofs are 0, each ``slaves[k]`` equals ``masters[k]``."""
    fixed_arr = np.unique(np.asarray(fixed, dtype=np.int64))
    slave_arr, master_arr = np.asarray(slaves, dtype=np.int64), np.asarray(masters, dtype=np.int64)
    if np.intersect1d(fixed_arr, slave_arr).size:
        raise ThermoelasticError("constraints: a dof is both fixed and tied")
    free = np.setdiff1d(np.arange(n_dof), np.concatenate([fixed_arr, slave_arr]))
    column = np.full(n_dof, -1, dtype=np.int64)
    column[free] = np.arange(free.size)
    column[slave_arr] = column[master_arr]  # a tie to a fixed master stays fixed (-1)
    rows = np.flatnonzero(column >= 0)
    return sp.csr_matrix((np.ones(rows.size), (rows, column[rows])), shape=(n_dof, free.size))


@dataclass(frozen=True, eq=False)
class ElasticSolver:
    """K and B reduced by the constraints and factorised once; ``expand`` maps mesh nodes to field nodes.

    ``expand[i]`` is the thermal node whose temperature mechanical node i takes (duplicated nodes of a
    floating surface take their original's temperature).
    """

    system: ElasticSystem
    T: sp.csr_matrix
    expand: NDArray[np.int64]
    n_field: int
    lu: spla.SuperLU

    @property
    def P(self) -> sp.csr_matrix:
        """(Nm, N) selection: mechanical-node temperature rise = P @ field-node temperature rise."""
        n = self.expand.size
        return sp.csr_matrix((np.ones(n), (np.arange(n), self.expand)), shape=(n, self.n_field))

    def displacement(self, delta_t: ArrayLike) -> Array:
        """Displacement (Nm, 2) [m] as (u_r, u_z) per mechanical node for a temperature rise (N,) [K]."""
        dt = np.asarray(delta_t, dtype=float)
        f = self.system.B @ dt[self.expand]
        u = self.T @ self.lu.solve(self.T.T @ f)
        return np.asarray(u[self.system.dofs].T)

    def adjoint(self, c: ArrayLike) -> Array:
        """g (N,) [m/K] with c·u = g·ΔT for every field: g = Pᵀ Bᵀ T (TᵀKT)⁻¹ Tᵀ c."""
        y = self.T @ self.lu.solve(self.T.T @ np.asarray(c, dtype=float))
        return np.asarray(self.P.T @ (self.system.B.T @ y))


def make_solver(
    system: ElasticSystem,
    *,
    fixed: ArrayLike,
    slaves: ArrayLike = (),
    masters: ArrayLike = (),
    expand: ArrayLike | None = None,
    n_field: int | None = None,
) -> ElasticSolver:
    """Apply the constraints and factorise TᵀKT (sparse LU); raise if a rigid-body mode is left."""
    n_mech = system.dofs.shape[1]
    exp = np.arange(n_mech) if expand is None else np.asarray(expand, dtype=np.int64)
    T = reduction(system.K.shape[0], fixed, slaves, masters)
    Kr = (T.T @ system.K @ T).tocsc()
    try:
        lu = spla.splu(Kr)
    except RuntimeError as err:
        raise ThermoelasticError(f"mechanics: stiffness singular ({err}); is the body held axially?") from err
    if not np.all(np.isfinite(lu.U.diagonal())) or np.min(np.abs(lu.U.diagonal())) < 1e-9 * abs(Kr).max():
        raise ThermoelasticError(
            "mechanics: stiffness singular; is every part held axially (mount, bearings)?"
        )
    return ElasticSolver(system, T, exp, int(n_mech if n_field is None else n_field), lu)


# ---------------------------------------------------------------- the spindle


@dataclass(frozen=True, eq=False)
class GrowthModel:
    """Growth operators of the spindle: output k [µm] = operators[k] · (T − T_ref) for a field T (N,) [°C].

    ``names``/``components``/``points_rz`` describe the outputs (``[[mechanics.outputs]]``); axial outputs
    are relative to the mounting face (held at u_z = 0). ``solver`` gives the full displacement when needed.
    """

    names: tuple[str, ...]
    components: tuple[str, ...]
    points_rz: Array  # (n_out, 2) [m]
    operators: Array  # (n_out, N) [µm/K]
    solver: ElasticSolver

    @property
    def n_nodes(self) -> int:
        """Number of thermal field nodes N."""
        return int(self.operators.shape[1])

    def operator(self, name: str) -> Array:
        """The operator g (N,) [µm/K] of one named output."""
        if name not in self.names:
            raise ThermoelasticError(f"name: unknown output {name!r}; outputs are {self.names}")
        return np.asarray(self.operators[self.names.index(name)])

    def rise(self, field_c: ArrayLike, t_ref_c: float | ArrayLike) -> Array:
        """ΔT = T − T_ref [K] for a field (..., N) and a scalar or (N,) reference [°C]."""
        t = np.asarray(field_c, dtype=float)
        if t.shape[-1] != self.n_nodes:
            raise ThermoelasticError(f"field_c: expected {self.n_nodes} nodes, got shape {t.shape}")
        ref = np.asarray(t_ref_c, dtype=float)
        if ref.ndim and ref.shape != (self.n_nodes,):
            raise ThermoelasticError(
                f"t_ref_c: expected a scalar or shape ({self.n_nodes},), got {ref.shape}"
            )
        return t - ref

    def growth_um(self, field_c: ArrayLike, t_ref_c: float | ArrayLike) -> Array:
        """All outputs [µm] for a field (N,) -> (n_out,) or fields (n, N) -> (n, n_out), by dot products."""
        return np.asarray(self.rise(field_c, t_ref_c) @ self.operators.T)

    def as_dict(self, growth_um: ArrayLike) -> dict[str, float]:
        """Name -> value [µm] for one (n_out,) vector."""
        return {n: float(v) for n, v in zip(self.names, np.asarray(growth_um), strict=True)}

    def reduced(self, phi: ArrayLike) -> Array:
        """g·Φ (n_out, r) [µm per unit reduced coordinate] for a basis Φ (N, r) of the field rise."""
        ph = np.asarray(phi, dtype=float)
        if ph.ndim != 2 or ph.shape[0] != self.n_nodes:
            raise ThermoelasticError(f"phi: expected shape ({self.n_nodes}, r), got {ph.shape}")
        return np.asarray(self.operators @ ph)

    def displacement_m(self, field_c: ArrayLike, t_ref_c: float | ArrayLike) -> Array:
        """Full displacement (Nm, 2) [m] (u_r, u_z) on the mechanical nodes (one sparse solve)."""
        return self.solver.displacement(self.rise(field_c, t_ref_c))


def _mechanics(spec: SpindleSpec) -> MechanicsSpec:
    if spec.mechanics is None:
        raise ThermoelasticError("mechanics: the spindle description has no [mechanics] section")
    return spec.mechanics


def element_properties(spec: SpindleSpec, element_region: NDArray[np.int64]) -> ElasticProperties:
    """E, ν, α of each element from its region's material (or the ``region_material`` override)."""
    mech = _mechanics(spec)
    mats = [spec.materials[mech.region_material.get(g.name, g.material)] for g in spec.regions]
    table = np.array([[m.e_pa, m.nu, m.alpha_per_k] for m in mats], dtype=float)
    if not np.all(np.isfinite(table)):
        bad = next(m.name for m in mats if m.e_pa is None)
        raise ThermoelasticError(f"materials.{bad}.e_pa: missing (E, nu, alpha_per_k needed by [mechanics])")
    per = table[element_region]
    return ElasticProperties(per[:, 0], per[:, 1], per[:, 2])


@dataclass(frozen=True)
class _Split:
    p: Array  # (2, Nm)
    t: NDArray[np.int64]  # (3, M)
    expand: NDArray[np.int64]  # (Nm,)
    slaves: NDArray[np.int64]  # duplicated nodes
    masters: NDArray[np.int64]  # their originals


def split_floating(spec: SpindleSpec, fe: FEModel) -> _Split:
    """Duplicate the nodes of each floating surface for the elements of its region (the sliding side)."""
    p, t = fe.nodes_rz.T.copy(), fe.triangles.T.copy()
    expand, slaves, masters = list(range(p.shape[1])), [], []
    names = [g.name for g in spec.regions]
    for i, fl in enumerate(_mechanics(spec).floating):
        idx = names.index(fl.region)
        g = spec.regions[idx]
        r_s = g.r1_m if fl.surface == "outer" else g.r0_m
        inside = fe.element_region == idx
        on = (np.abs(p[0] - r_s) < _TOL) & (p[1] > g.z0_m - _TOL) & (p[1] < g.z1_m + _TOL)
        shared = np.flatnonzero(on & _used(t[:, inside], p.shape[1]) & _used(t[:, ~inside], p.shape[1]))
        if shared.size < 2:
            raise ThermoelasticError(
                f"mechanics.floating[{i}].surface: region {fl.region!r} touches no other solid at r = {r_s}"
            )
        new = np.arange(p.shape[1], p.shape[1] + shared.size)
        remap = np.arange(p.shape[1] + shared.size)
        remap[shared] = new
        t[:, inside] = remap[t[:, inside]]
        p = np.hstack([p, p[:, shared]])
        expand += [expand[s] for s in shared]
        slaves += new.tolist()
        masters += shared.tolist()
    return _Split(p, t, np.array(expand), np.array(slaves, dtype=np.int64), np.array(masters, dtype=np.int64))


def _used(t: NDArray[np.int64], n: int) -> NDArray[np.bool_]:
    mask = np.zeros(n, dtype=bool)
    mask[t.ravel()] = True
    return mask


def _on_segment(p: Array, seg: Segment2D) -> NDArray[np.bool_]:
    r_lo, r_hi = sorted((seg.r0_m, seg.r1_m))
    z_lo, z_hi = sorted((seg.z0_m, seg.z1_m))
    return np.asarray(
        (p[0] > r_lo - _TOL) & (p[0] < r_hi + _TOL) & (p[1] > z_lo - _TOL) & (p[1] < z_hi + _TOL)
    )


def _mount_nodes(spec: SpindleSpec, split: _Split) -> list[NDArray[np.int64]]:
    out = []
    for i, seg in enumerate(_mechanics(spec).mount.segments):
        nodes = np.flatnonzero(_on_segment(split.p, seg) & _used(split.t, split.p.shape[1]))
        if nodes.size < 2:
            raise ThermoelasticError(f"mechanics.mount.segments[{i}]: no edge of the mesh lies on it")
        out.append(nodes)
    return out


def _fixed_dofs(spec: SpindleSpec, split: _Split, dofs: NDArray[np.int64], fix: str) -> NDArray[np.int64]:
    fixed = [dofs[0, np.abs(split.p[0]) < _TOL]]  # symmetry axis: u_r = 0
    for nodes in _mount_nodes(spec, split):
        fixed.append(dofs[1, nodes])
        if fix == "axial_radial":
            fixed.append(dofs[0, nodes])
    return np.unique(np.concatenate(fixed))


def mount_spring(
    spec: SpindleSpec, split: _Split, dofs: NDArray[np.int64], stiffness_pa_per_m: float
) -> sp.csr_matrix:
    """Radial Winkler spring on the mounting face: k [Pa/m = N/m per m² of face] on u_r, lumped per node.

    Node i of a face segment carries k · 2π r_i · ℓ_i [N/m], ℓ_i half the length of its face edges
    (trapezoidal rule of ∫ k u_r v_r 2πr ds): the flange's radial friction/bolt stiffness against the spindle
    head, between free (k = 0) and held (k → ∞)."""
    n = int(dofs.max()) + 1
    diag = np.zeros(n)
    for nodes in _mount_nodes(spec, split):
        pts = split.p[:, nodes]
        s = np.hypot(pts[0] - pts[0, 0], pts[1] - pts[1, 0])  # arc length along the straight segment
        order = np.argsort(s)
        s_sorted = s[order]
        edge = np.diff(s_sorted)
        half = np.zeros(s_sorted.size)
        half[:-1] += 0.5 * edge
        half[1:] += 0.5 * edge
        diag[dofs[0, nodes[order]]] += stiffness_pa_per_m * TWO_PI * pts[0, order] * half
    return sp.diags(diag).tocsr()


def _selectors(spec: SpindleSpec, mesh: MeshTri, dofs: NDArray[np.int64]) -> NDArray[np.float64]:
    outs = _mechanics(spec).outputs
    pts = np.array([[o.r_m for o in outs], [o.z_m for o in outs]])
    try:
        probe = sp.csr_matrix(Basis(mesh, ElementTriP1()).probes(pts)).toarray()
    except ValueError as err:
        raise ThermoelasticError(f"mechanics.outputs: a point lies outside the mesh ({err})") from err
    c = np.zeros((len(outs), int(dofs.max()) + 1))
    for k, o in enumerate(outs):
        c[k, dofs[0 if o.component == "radial" else 1]] = probe[k]
    return c


@dataclass(frozen=True)
class MechanicsVariant:
    """What a plant's mechanics change against the spindle description (all neutral by default).

    ``fix``: the mount's fixing, None keeps ``[mechanics.mount].fix``; ``mount_spring_pa_per_m``: a radial
    Winkler spring on the mounting face [N/m per m²] (only with an axial fix: between free and held);
    ``region_alpha_scale`` / ``region_e_scale``: per region (in ``spec.regions`` order) factors on α and E;
    ``floating``: False fuses the floating surfaces (a stuck rear bearing)."""

    fix: str | None = None
    mount_spring_pa_per_m: float = 0.0
    region_alpha_scale: tuple[float, ...] | None = None
    region_e_scale: tuple[float, ...] | None = None
    floating: bool = True


def _scaled(
    spec: SpindleSpec, props: ElasticProperties, region: NDArray[np.int64], v: MechanicsVariant
) -> ElasticProperties:
    n = len(spec.regions)
    a = np.ones(n) if v.region_alpha_scale is None else np.asarray(v.region_alpha_scale, dtype=float)
    e = np.ones(n) if v.region_e_scale is None else np.asarray(v.region_e_scale, dtype=float)
    if a.shape != (n,) or e.shape != (n,) or not (np.all(np.isfinite(a)) and np.all(e > 0)):
        raise ThermoelasticError(f"variant: region scales must be {n} finite values (E scales > 0)")
    return ElasticProperties(props.e_pa * e[region], props.nu, props.alpha_per_k * a[region])


def build_growth_model(
    spec: SpindleSpec, fe: FEModel, *, variant: MechanicsVariant | None = None
) -> GrowthModel:
    """Assemble, constrain and factorise the thermoelastic model on ``fe``'s mesh; precompute the operators.

    ``variant`` (a plant's own mechanics, ``model.plantmech``) changes the mount, α, E or the floating
    bearing; None is the description as written. Cost: one sparse LU of about 2N dofs and one
    back-substitution per output (about a second at the default mesh); afterwards every evaluation is
    ``operators @ ΔT``.
    """
    mech = _mechanics(spec)
    v = variant if variant is not None else MechanicsVariant()
    fix = mech.mount.fix if v.fix is None else v.fix
    if fix not in ("axial", "axial_radial"):
        raise ThermoelasticError(f"variant.fix: must be axial or axial_radial, got {fix!r}")
    if not (np.isfinite(v.mount_spring_pa_per_m) and v.mount_spring_pa_per_m >= 0):
        raise ThermoelasticError(
            f"variant.mount_spring_pa_per_m: must be >= 0, got {v.mount_spring_pa_per_m}"
        )
    split = split_floating(spec, fe) if v.floating else _no_split(fe)
    props = _scaled(spec, element_properties(spec, fe.element_region), fe.element_region, v)
    system = assemble_elasticity(split.p, split.t, props)
    if v.mount_spring_pa_per_m > 0 and fix == "axial":
        spring = mount_spring(spec, split, system.dofs, v.mount_spring_pa_per_m)
        system = ElasticSystem(system.mesh, (system.K + spring).tocsr(), system.B, system.dofs)
    solver = make_solver(
        system,
        fixed=_fixed_dofs(spec, split, system.dofs, fix),
        slaves=system.dofs[0, split.slaves],
        masters=system.dofs[0, split.masters],
        expand=split.expand,
        n_field=fe.n_nodes,
    )
    ops = np.array([solver.adjoint(c) for c in _selectors(spec, system.mesh, system.dofs)]) * M_TO_UM
    return GrowthModel(
        names=tuple(o.name for o in mech.outputs),
        components=tuple(o.component for o in mech.outputs),
        points_rz=np.array([[o.r_m, o.z_m] for o in mech.outputs]),
        operators=ops,
        solver=solver,
    )


def _no_split(fe: FEModel) -> _Split:
    empty = np.zeros(0, dtype=np.int64)
    return _Split(fe.nodes_rz.T.copy(), fe.triangles.T.copy(), np.arange(fe.n_nodes), empty, empty)
