"""Offline part of the reduced model: full-FE snapshots, POD basis and the affine Galerkin projection.

Works on any *affine system* (``AffineSystem``): heat capacity E, conductance K0, per-zone boundary matrices
K_i, per-zone ambient load vectors z_i, unit (1 W) bearing load vectors q_front/q_rear and the sensor
interpolation operator. ``model.fem.FEModel`` is one; the tests also use a small stand-in.

Snapshots (per H sample of the box: both corners plus a log-uniform Latin hypercube; all with the exact
θ-method of the full FE; scaled by realistic amplitudes so that the POD weighs them as they occur):
- cooling of a uniform 10 °C field towards a 0 °C ambient (the ambient-step response; the uniform field
  itself is exact in the basis);
- front and rear bearing-heat steps (q_max W) from 0 °C;
- free response of two non-uniform starts (a steady field of the previous H sample, a mid-transient one);
- per-zone boundary layers: the first steps after a surface-temperature mismatch on one zone alone;
- the steady fields K(H)⁻¹·q_front, K(H)⁻¹·q_rear and their sensitivities H_i·∂T/∂H_i.
The time grid is Δt = 10 s for the first 5 min (where the fast modes live), then 30 s and 120 s up to ~2 h.
The snapshots are weighted with the lumped heat capacity plus extra rows for the 32 sensor values, made
constant-free, compressed per H sample (method of snapshots), then merged across samples by a second
compression; the uniform field is put first and the basis is made E-orthonormal.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from numpy.typing import NDArray

Array = NDArray[np.float64]

# (Δt [s], number of steps) of the snapshot trajectories: 5 min at 10 s, 15 min at 30 s, 90 min at 120 s.
SNAPSHOT_SCHEDULE: tuple[tuple[float, int], ...] = ((10.0, 30), (30.0, 30), (120.0, 45))
SNAPSHOT_STRIDE: tuple[int, ...] = (3, 3, 5)  # keep every k-th state (and the first 6 at 10 s)
LAYER_STEPS: tuple[int, ...] = (1, 2, 3, 6)  # steps (of 10 s) kept of the per-zone boundary-layer responses


class AffineSystem(Protocol):
    """The affine-in-H full model: E·dT/dt + (K0 + Σ H_i·K_i)·T = T_amb·Σ H_i·z_i + Q_f·q_f + Q_r·q_r."""

    @property
    def E(self) -> Any: ...  # sparse (N, N) [J/K]

    @property
    def K0(self) -> Any: ...  # sparse (N, N) [W/K]

    @property
    def K_zone(self) -> Sequence[Any]: ...  # 7 sparse (N, N) [m²] (times H -> W/K)

    @property
    def z_zone(self) -> Any: ...  # (7, N) [m²]

    @property
    def q_front(self) -> Any: ...  # (N,) load per 1 W

    @property
    def q_rear(self) -> Any: ...  # (N,) load per 1 W

    @property
    def sensor_op(self) -> Any: ...  # sparse (32, N)


def conductance(fe: AffineSystem, h: Array) -> Any:
    """Full conductance K(H) = K0 + Σ H_i·K_i (sparse CSC, W/K) for H (7,) in W/(m²·K)."""
    k = sp.csc_matrix(fe.K0, dtype=np.float64, copy=True)
    for hi, ki in zip(h, fe.K_zone, strict=True):
        k = k + float(hi) * ki
    return sp.csc_matrix(k)


def ambient_vector(fe: AffineSystem, h: Array) -> Array:
    """Σ H_i·z_i (N,) [W/K]: the load per 1 °C of ambient temperature."""
    return np.asarray(h, dtype=np.float64) @ np.asarray(fe.z_zone, dtype=np.float64)


@dataclass(frozen=True)
class Stepper:
    """Factorised θ-method step for one H and one Δt: (E/Δt + θK)·x⁺ = (E/Δt − (1−θ)K)·x + f."""

    solve: Any
    rhs_op: Any

    def step(self, x: Array, load: Array) -> Array:
        """One step for the columns of ``x`` (N,) or (N, k) with load ``load`` (same shape) [W]."""
        return np.asarray(self.solve(np.asarray(self.rhs_op @ x + load)))


def factorize(a: Any) -> Any:
    """Sparse LU of a symmetric matrix (minimum-degree ordering on A+Aᵀ); returns its ``solve``."""
    return spla.splu(sp.csc_matrix(a), permc_spec="MMD_AT_PLUS_A").solve


def make_stepper(fe: AffineSystem, k: Any, dt_s: float, theta: float) -> Stepper:
    """Factorise the θ-method step matrix once (sparse LU)."""
    e_dt = sp.csc_matrix(fe.E) / dt_s
    rhs = sp.csr_matrix(e_dt - (1.0 - theta) * k)
    return Stepper(solve=factorize(e_dt + theta * k), rhs_op=rhs)


def reference_sensors(
    fe: AffineSystem,
    h: Array,
    *,
    dt_s: float,
    ambient_c: Array,
    q_front_w: Array,
    q_rear_w: Array,
    t0: Array,
    theta: float,
    load_scale: tuple[float, float] = (1.0, 1.0),
    substeps: int = 1,
) -> Array:
    """Full-FE θ-method sensor trajectories [°C] for one H, inputs piecewise constant per step.

    ``substeps``: θ-method steps of ``dt_s``/substeps per input step (sensors kept at the input steps): a
    finer time step for a reference that converges towards the exact solution of the held inputs.

    Inputs (n_steps,) with t0 (N,) give (n_steps+1, 32); inputs (n_steps, k) with t0 (N, k) run k histories
    at once (one factorisation, multi-column solves) and give (k, n_steps+1, 32). Input entry k applies on
    step k -> k+1, as in ``model.fem.simulate``.
    """
    single = np.ndim(ambient_c) == 1
    amb_in, qf_in, qr_in = (
        np.asarray(a, dtype=np.float64).reshape(len(a), -1) for a in (ambient_c, q_front_w, q_rear_w)
    )
    x = np.asarray(t0, dtype=np.float64).reshape(fe.E.shape[0], -1).copy()
    k = conductance(fe, h)
    sub = max(int(substeps), 1)
    stepper = make_stepper(fe, k, dt_s / sub, theta)
    amb = ambient_vector(fe, h)[:, None]
    qf = np.asarray(fe.q_front, dtype=np.float64)[:, None] * load_scale[0]
    qr = np.asarray(fe.q_rear, dtype=np.float64)[:, None] * load_scale[1]
    sens = sp.csr_matrix(fe.sensor_op)
    out = np.empty((x.shape[1], amb_in.shape[0] + 1, sens.shape[0]))
    out[:, 0, :] = (sens @ x).T
    for n in range(amb_in.shape[0]):
        load = amb * amb_in[n] + qf * qf_in[n] + qr * qr_in[n]
        for _ in range(sub):
            x = stepper.step(x, load)
        out[:, n + 1, :] = (sens @ x).T
    return out[0] if single else out


def steady_field(fe: AffineSystem, h: Array, *, ambient_c: float, q_front_w: float, q_rear_w: float) -> Array:
    """Full-FE steady state K(H)⁻¹·Z (N,) [°C]."""
    load = (
        ambient_c * ambient_vector(fe, h)
        + q_front_w * np.asarray(fe.q_front)
        + q_rear_w * np.asarray(fe.q_rear)
    )
    return np.asarray(spla.spsolve(conductance(fe, h), load))


def log_latin_hypercube(n: int, box: tuple[float, float], *, rng: np.random.Generator, dim: int = 7) -> Array:
    """n points (n, dim) in the box, log-uniform Latin hypercube [W/(m²·K)]."""
    lo, hi = box
    ranks = np.argsort(rng.random((dim, n)), axis=1).T
    u = (ranks + rng.random((n, dim))) / n
    return np.asarray(lo * (hi / lo) ** u)


def training_h(n: int, box: tuple[float, float], *, rng: np.random.Generator, dim: int = 7) -> Array:
    """Training H samples: both corners of the box plus an n-point log-uniform Latin hypercube."""
    lo, hi = box
    return np.vstack([np.full(dim, lo), np.full(dim, hi), log_latin_hypercube(n, box, rng=rng, dim=dim)])


def _trajectory_snapshots(
    fe: AffineSystem, k: Any, x0: Array, loads: Array, theta: float, substeps: int = 1
) -> list[Array]:
    """States along ``SNAPSHOT_SCHEDULE`` for the columns of x0 (N, m) under constant loads (N, m);
    ``substeps`` θ-steps per step of the first (10-s) part, where the fast modes live."""
    snaps: list[Array] = []
    x = x0
    for i, (dt_s, n_steps) in enumerate(SNAPSHOT_SCHEDULE):
        sub = max(int(substeps), 1) if i == 0 else 1
        stepper = make_stepper(fe, k, dt_s / sub, theta)
        for n in range(1, n_steps + 1):
            for _ in range(sub):
                x = stepper.step(x, loads)
            if n % SNAPSHOT_STRIDE[i] == 0 or (i == 0 and n <= 6):
                snaps.append(x)
    return snaps


@dataclass(frozen=True)
class Amplitudes:
    """Input amplitudes that scale the snapshots, so the POD weighs them as they occur [°C, W, W]."""

    ambient_c: float
    q_front_w: float
    q_rear_w: float


@dataclass(frozen=True)
class SampleSnapshots:
    """Snapshots of one H sample (N, m) [°C] and two non-uniform start fields for the next sample."""

    states: Array
    steady: Array
    transient: Array


def sample_snapshots(
    fe: AffineSystem,
    h: Array,
    *,
    theta: float,
    amp: Amplitudes,
    starts: tuple[Array, Array],
    rng: np.random.Generator,
    substeps: int = 1,
) -> SampleSnapshots:
    """Full-FE θ-method snapshots for one H (7,): input-step and free responses, steady fields and their
    sensitivities H_i·∂T/∂H_i. ``substeps`` > 1: the 10-s part of the trajectories and the boundary layers
    are stepped at 10 s / substeps (states kept at the same times), closer to the exact time response that
    a reduced model integrated exactly over each step reproduces."""
    n = fe.E.shape[0]
    k = conductance(fe, h)
    qf = np.asarray(fe.q_front, dtype=np.float64) * amp.q_front_w
    qr = np.asarray(fe.q_rear, dtype=np.float64) * amp.q_rear_w
    x0 = np.zeros((n, 5))
    x0[:, 0] = amp.ambient_c
    x0[:, 3], x0[:, 4] = starts
    loads = np.zeros((n, 5))
    loads[:, 1], loads[:, 2] = qf, qr
    snaps = _trajectory_snapshots(fe, k, x0, loads, theta, substeps)
    solve = factorize(k)
    steady = np.asarray(solve(np.column_stack([qf, qr])))
    surfaces = np.column_stack([np.full(n, amp.ambient_c), steady, starts[0]])  # starts[0]: another H's field
    layers = zone_layers(fe, h, k, theta, surfaces, substeps)
    sens = steady_sensitivities(fe, h, steady, solve)
    mix = rng.random(3)
    mid = snaps[int(rng.integers(0, len(snaps)))]
    return SampleSnapshots(
        states=np.column_stack([np.hstack(snaps), layers, steady, sens]),
        steady=steady @ mix[:2],
        transient=mid[:, 1] * mix[0] + mid[:, 2] * mix[1] + mid[:, 0] * mix[2],
    )


def zone_layers(fe: AffineSystem, h: Array, k: Any, theta: float, surface: Array, substeps: int = 1) -> Array:
    """Boundary layers of each zone: the first steps at Δt = 10 s of a 0 °C body whose zone i alone is
    loaded by H_i·K_i·x for each surface temperature field x in ``surface`` (N, m) [°C].

    They carry little energy but sit under the surface sensors right after a change of ambient or of H,
    so they get their own snapshots, (N, 7·m·len(LAYER_STEPS)).
    """
    sub = max(int(substeps), 1)
    stepper = make_stepper(fe, k, SNAPSHOT_SCHEDULE[0][0] / sub, theta)
    loads = np.hstack([float(hi) * np.asarray(ki @ surface) for hi, ki in zip(h, fe.K_zone, strict=True)])
    x = np.zeros_like(loads)
    out = []
    for n in range(1, max(LAYER_STEPS) + 1):
        for _ in range(sub):
            x = stepper.step(x, loads)
        if n in LAYER_STEPS:
            out.append(x)
    return np.hstack(out)


def steady_sensitivities(fe: AffineSystem, h: Array, steady: Array, solve: Any) -> Array:
    """Scaled derivatives H_i·∂x/∂H_i = −H_i·K⁻¹·K_i·x of the steady fields x (N, m) -> (N, 7·m)."""
    rhs = np.hstack([-float(hi) * (ki @ steady) for hi, ki in zip(h, fe.K_zone, strict=True)])
    return np.asarray(solve(rhs))


def lumped_mass(fe: AffineSystem) -> Array:
    """Row sums of E (N,) [J/K]: the weights of the POD inner product."""
    return np.asarray(sp.csr_matrix(fe.E).sum(axis=1)).ravel()


def _leading_modes(w: Array, keep: int, rel_tol: float) -> tuple[Array, Array]:
    """Left singular vectors times singular values U·Σ (N, ≤keep) and all singular values, via the Gram
    matrix (method of snapshots: cheap for many rows, accurate enough for σ/σ₀ ≫ 1e-8)."""
    gram = w.T @ w
    ev, vec = np.linalg.eigh(0.5 * (gram + gram.T))
    ev, vec = ev[::-1], vec[:, ::-1]
    sing = np.sqrt(np.clip(ev, 0.0, None))
    n_keep = min(keep, int(np.count_nonzero(sing > rel_tol * sing[0]))) if sing[0] > 0 else 0
    return w @ vec[:, :n_keep], sing


@dataclass(frozen=True)
class Weighting:
    """POD inner product: lumped heat capacity on the field plus ``sensor_weight``² on the 32 sensor values.

    The sensor rows make the POD care about what the sensors see (thin boundary layers after input steps
    carry little energy but sit right under the housing sensors).
    """

    sqrt_m: Array
    sensor_op: Any
    sensor_weight: float

    @classmethod
    def of(cls, fe: AffineSystem, sensor_factor: float) -> Weighting:
        """Sensor weight = ``sensor_factor``·sqrt(total heat capacity / 32): both parts weigh alike at 1."""
        m = lumped_mass(fe)
        n_sens = fe.sensor_op.shape[0]
        return cls(np.sqrt(m), sp.csr_matrix(fe.sensor_op), sensor_factor * float(np.sqrt(m.sum() / n_sens)))

    def apply(self, x: Array) -> Array:
        """Weighted rows [√m·x ; w·S·x] ((N+32), k) of constant-free fields x (N, k)."""
        return np.vstack([x * self.sqrt_m[:, None], self.sensor_weight * np.asarray(self.sensor_op @ x)])

    def remove_constant(self, x: Array) -> Array:
        """Subtract the E-orthogonal (lumped) projection onto the uniform field."""
        m = self.sqrt_m**2
        return x - np.outer(np.ones(m.size), (m @ x) / m.sum())


def compress(snap: SampleSnapshots, weighting: Weighting, *, keep: int, rel_tol: float = 1e-7) -> Array:
    """Weighted, constant-free, compressed snapshots U·Σ ((N+32), ≤keep) of one H sample."""
    w = weighting.apply(weighting.remove_constant(snap.states))
    return _leading_modes(w, keep, rel_tol)[0]


def pod_basis(
    blocks: Sequence[Array], fe: AffineSystem, weighting: Weighting, rank: int
) -> tuple[Array, Array]:
    """E-orthonormal basis V (N, rank) with the uniform field first, and the POD singular values.

    ``blocks`` are the outputs of ``compress``, one per H sample.
    """
    n = fe.E.shape[0]
    us, sing = _leading_modes(np.hstack(list(blocks)), rank - 1, 0.0)
    modes = us[:n] / weighting.sqrt_m[:, None]
    modes /= np.linalg.norm(modes, axis=0)
    v = np.column_stack([np.ones(n) / np.sqrt(n), modes])
    return e_orthonormalise(fe, v), sing


def e_orthonormalise(fe: AffineSystem, v: Array) -> Array:
    """Gram–Schmidt in the E inner product via Cholesky (keeps the span and the order of the columns)."""
    for _ in range(2):  # twice is enough (CGS2)
        gram = v.T @ (fe.E @ v)
        chol = np.linalg.cholesky(0.5 * (gram + gram.T))
        v = sla.solve_triangular(chol, v.T, lower=True).T
    return np.asarray(v)


@dataclass(frozen=True)
class Projection:
    """Galerkin-projected affine operators (E_r = I by construction)."""

    k0: Array  # (r, r) W/K
    k_zone: Array  # (7, r, r) m²
    z_zone: Array  # (7, r) m²
    q_front: Array  # (r,) per W
    q_rear: Array  # (r,) per W
    sensors: Array  # (32, r)
    basis_t_mass: Array  # (r, N): a = Vᵀ·E·T projects a field


def project_system(fe: AffineSystem, v: Array) -> Projection:
    """Project once: K0_r = VᵀK0V, K_i,r = VᵀK_iV, z_i,r = Vᵀz_i, q_r = Vᵀq, S_r = S·V."""

    def sym(a: Array) -> Array:
        return 0.5 * (a + a.T)

    return Projection(
        k0=sym(v.T @ (fe.K0 @ v)),
        k_zone=np.stack([sym(v.T @ (ki @ v)) for ki in fe.K_zone]),
        z_zone=np.asarray(fe.z_zone, dtype=np.float64) @ v,
        q_front=np.asarray(fe.q_front, dtype=np.float64) @ v,
        q_rear=np.asarray(fe.q_rear, dtype=np.float64) @ v,
        sensors=np.asarray(fe.sensor_op @ v),
        basis_t_mass=np.asarray((fe.E @ v).T),
    )
