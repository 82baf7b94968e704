"""The reduced model over a window whose H change from segment to segment, for a population of candidates.

``model.rom.ReducedModel`` evaluates one H per candidate over a whole window. A window with speed changes
has H_s for segment s (S segments): K_r(H_s) = K0_r + Σ H_s,i·K_i,r switches at each segment start while the
reduced state carries over (the state is continuous; only the operator changes, as in the full FE with a
time-varying K(H)). This module steps the reduced model with the ROM's own discrete step
(``rom.substeps``, ``model.rom_modal.step_factors``: 0 = the exact solution with the input held over each
step, s ≥ 1 = s θ-steps of Δt/s)::

    a(k+1) = A_s·a(k) + G_s·z_k,   A_s = Φ_s·diag(μ)·Φ_sᵀ,  G_s = Φ_s·diag(γ)·Φ_sᵀ,
    z_k = Ti_k·Σ H_s,i·z_i + Qf_k·q_f + Qr_k·q_r,   K_s = K0_r + Σ H_s,i·K_i,r = Φ_s·diag(λ)·Φ_sᵀ

with one eigendecomposition of K_s per (candidate, segment) (batched LAPACK); each segment runs in its modes
(b = Φ_sᵀ·a: b(k+1) = μ∘b(k) + γ∘Φ_sᵀ·z_k, a diagonal recursion done in vectorised blocks by
``rom_modal.blocked_recursion``; the state goes back through Φ_s at the segment's end). The tangent model
differentiates A_s and G_s as matrix functions of K_s (Daleckii–Krein: the derivative of f(K) along δK
is Φ·(L_f ∘ Φᵀ·δK·Φ)·Φᵀ with L_f the divided differences of f over the eigenvalues), so it is exact for
every ``substeps``; the tangents step in the same modes. It reads the public arrays of a ``ReducedModel``
(k0, k_zone, z_zone, q_front, q_rear, sensors, theta, substeps, initial_state, lift) and changes nothing
there; with one segment it reproduces ``simulate_sensors`` to round-off (a test checks it).

Errors::

    SegmentError(ValueError)   bad segment index, H shape or inputs (the argument is named)
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from model import rom_modal
from model.errors import ModelError

Array = NDArray[np.float64]


class SegmentError(ModelError, ValueError):
    """A bad argument to the segmented evaluation; the message names it."""


@dataclass(frozen=True)
class SegmentPlan:
    """Which H segment each step uses: ``of_step`` (n_steps,) in 0..S-1; ``start`` (S,) first step of each."""

    of_step: NDArray[np.int64]
    start: NDArray[np.int64]

    @property
    def n_segments(self) -> int:
        """Number of segments S."""
        return int(self.start.size)

    @property
    def n_steps(self) -> int:
        """Number of steps of the window."""
        return int(self.of_step.size)


def plan_from_speed(speed_rpm: ArrayLike) -> SegmentPlan:
    """Segments of constant speed from the per-step speed (n_steps,) [rpm] (entry k applies on step k→k+1)."""
    n = np.asarray(speed_rpm, dtype=np.float64)
    if n.ndim != 1 or n.size == 0 or not np.all(np.isfinite(n)):
        raise SegmentError(f"speed_rpm: expected a non-empty 1-D finite array, got shape {n.shape}")
    start = np.concatenate([[0], np.flatnonzero(np.diff(n) != 0.0) + 1]).astype(np.int64)
    of_step = (np.cumsum(np.isin(np.arange(n.size), start)) - 1).astype(np.int64)
    return SegmentPlan(of_step=of_step, start=start)


def segment_means(plan: SegmentPlan, values: ArrayLike) -> Array:
    """Mean of a per-step series (n_steps,) over each segment: (S,) (e.g. the ambient that sets H_s)."""
    v = np.asarray(values, dtype=np.float64)
    if v.shape != (plan.n_steps,):
        raise SegmentError(f"values: expected shape ({plan.n_steps},), got {v.shape}")
    sums = np.bincount(plan.of_step, weights=v, minlength=plan.n_segments)
    return np.asarray(sums / np.bincount(plan.of_step, minlength=plan.n_segments))


def _inputs(inputs: Any, n_steps: int) -> tuple[float, Array, Array, Array]:
    dt = float(inputs.dt_s)
    if not (np.isfinite(dt) and dt > 0.0):
        raise SegmentError(f"inputs.dt_s: must be > 0 s, got {inputs.dt_s}")
    out = []
    for name in ("ambient_c", "q_front_w", "q_rear_w"):
        a = np.asarray(getattr(inputs, name), dtype=np.float64)
        if a.shape != (n_steps,) or not np.all(np.isfinite(a)):
            raise SegmentError(f"inputs.{name}: expected {n_steps} finite values, got shape {a.shape}")
        out.append(a)
    return dt, out[0], out[1], out[2]


def _check_h(h_seg: ArrayLike, plan: SegmentPlan) -> Array:
    h = np.asarray(h_seg, dtype=np.float64)
    if h.ndim != 3 or h.shape[1:] != (plan.n_segments, 7):
        raise SegmentError(f"h_seg: expected shape (P, {plan.n_segments}, 7), got {h.shape}")
    if not np.all(np.isfinite(h)) or np.any(h <= 0.0):
        raise SegmentError("h_seg: every coefficient must be finite and > 0 W/(m²·K)")
    return h


@dataclass(frozen=True)
class Operators:
    """Per (candidate, segment), (P, S, ...): the eigenpairs ``lam``, ``phi`` of K_s, the step's factors
    ``mu``, ``gamma`` (P, S, r) (the step matrices are A = Φ·diag(μ)·Φᵀ and G = Φ·diag(γ)·Φᵀ) and the
    divided differences ``l_mu``, ``l_gamma`` (P, S, r, r) of μ(λ) and γ(λ) (``loewner``) that give their
    derivatives."""

    lam: Array
    phi: Array
    mu: Array
    gamma: Array
    l_mu: Array
    l_gamma: Array


def step_derivatives(lam: Array, dt_s: float, theta: float, substeps: int) -> tuple[Array, Array]:
    """dμ/dλ and dγ/dλ [s, s²] of ``rom_modal.step_factors`` (same shape as ``lam``; λ > 0 [1/s])."""
    mu, gamma = rom_modal.step_factors(lam, dt_s, theta, substeps)
    if substeps == 0:
        dmu = -dt_s * mu
    else:
        inv_h = substeps / dt_s
        m = (inv_h - (1.0 - theta) * lam) / (inv_h + theta * lam)
        dmu = substeps * m ** (substeps - 1) * (-inv_h / (inv_h + theta * lam) ** 2)
    with np.errstate(divide="ignore", invalid="ignore"):
        dgamma = np.where(lam > 0.0, (-dmu - gamma) / np.where(lam > 0.0, lam, 1.0), -0.5 * dt_s**2)
    return np.asarray(dmu), np.asarray(dgamma)


def loewner(lam: Array, f: Array, df: Array) -> Array:
    """Divided differences (..., r, r) of f over the eigenvalues (..., r): (f_j − f_k)/(λ_j − λ_k), and the
    mean of f′ where λ_j ≈ λ_k. Then d f(K)[δK] = Φ·(L ∘ Φᵀ·δK·Φ)·Φᵀ (Daleckii–Krein)."""
    dl = lam[..., :, None] - lam[..., None, :]
    close = np.abs(dl) <= 1e-9 * np.max(np.abs(lam), axis=-1, keepdims=True)[..., None]
    with np.errstate(divide="ignore", invalid="ignore"):
        diff = (f[..., :, None] - f[..., None, :]) / np.where(close, 1.0, dl)
    return np.asarray(np.where(close, 0.5 * (df[..., :, None] + df[..., None, :]), diff))


def operators(rom: Any, h: Array, dt: float) -> Operators:
    """The step of every (candidate, segment) for H (P, S, 7) and Δt [s] (``Operators``)."""
    r = rom.k0.shape[0]
    p, s, _ = h.shape
    k = (h.reshape(p * s, 7) @ rom.k_zone.reshape(7, r * r)).reshape(p, s, r, r) + rom.k0
    lam, phi = np.linalg.eigh(k)
    theta, substeps = float(rom.theta), int(getattr(rom, "substeps", 1))
    mu, gamma = rom_modal.step_factors(lam, dt, theta, substeps)
    dmu, dgamma = step_derivatives(lam, dt, theta, substeps)
    return Operators(lam, phi, mu, gamma, loewner(lam, mu, dmu), loewner(lam, gamma, dgamma))


def _start(rom: Any, t0: float | ArrayLike, p: int) -> Array:
    a0 = np.asarray(t0, dtype=np.float64)
    r = rom.k0.shape[0]
    if a0.ndim == 2 and a0.shape == (p, r):
        return a0.copy()  # reduced start states per candidate
    return np.broadcast_to(rom.initial_state(t0 if a0.ndim else float(a0)), (p, r)).copy()


def simulate_states(
    rom: Any, h_seg: ArrayLike, plan: SegmentPlan, inputs: Any, t0: float | ArrayLike
) -> Array:
    """Reduced states (P, n_steps+1, r) for P candidates with H per segment ``h_seg`` (P, S, 7) [W/(m²·K)].

    ``t0``: uniform start [°C], an (N,) field (projected) or (P, r) reduced start states.
    """
    return simulate_run(rom, h_seg, plan, inputs, t0)[0]


def simulate_run(
    rom: Any, h_seg: ArrayLike, plan: SegmentPlan, inputs: Any, t0: float | ArrayLike
) -> tuple[Array, Operators]:
    """``simulate_states`` and the step operators it used (``simulate_tangents(run=...)`` reuses both)."""
    return _run(rom, _check_h(h_seg, plan), plan, inputs, t0)


def _run(
    rom: Any, h: Array, plan: SegmentPlan, inputs: Any, t0: float | ArrayLike
) -> tuple[Array, Operators]:
    """``simulate_states`` for checked H (P, S, 7), with the step operators it used.

    Each segment runs in its modes (A_s = Φ·diag(μ)·Φᵀ, G_s = Φ·diag(γ)·Φᵀ): b = Φᵀ·a steps as
    b⁺ = μ∘b + γ∘Φᵀ·z, a diagonal recursion done in vectorised blocks (``rom_modal.blocked_recursion``)."""
    dt, amb, qf, qr = _inputs(inputs, plan.n_steps)
    ops = operators(rom, h, dt)
    p = h.shape[0]
    hz = h @ rom.z_zone  # (P, S, r): ambient load per °C
    out = np.empty((p, plan.n_steps + 1, rom.k0.shape[0]))
    out[:, 0] = _start(rom, t0, p)
    ends = np.append(plan.start[1:], plan.n_steps)
    for s, (k0, k1) in enumerate(zip(plan.start.tolist(), ends.tolist(), strict=True)):
        phi = ops.phi[:, s]  # (P, r, r)
        z = (
            amb[None, k0:k1, None] * hz[:, s, None, :]
            + qf[k0:k1, None] * rom.q_front
            + qr[k0:k1, None] * rom.q_rear
        )  # (P, n_s, r): z_k for all steps of the segment
        y = np.empty((k1 - k0 + 1, p, phi.shape[1]))
        y[0] = np.einsum("pr,prs->ps", out[:, k0], phi)  # Φᵀ·a(k0)
        y[1:] = np.swapaxes((z @ phi) * ops.gamma[:, s, None, :], 0, 1)  # γ∘Φᵀ·z_k
        rom_modal.blocked_recursion(y, ops.mu[:, s])
        out[:, k0 + 1 : k1 + 1] = np.swapaxes(y[1:], 0, 1) @ np.swapaxes(phi, 1, 2)
    return out, ops


def simulate_sensors(
    rom: Any, h_seg: ArrayLike, plan: SegmentPlan, inputs: Any, t0: float | ArrayLike
) -> Array:
    """Sensor temperatures (P, n_steps+1, 32) [°C] for H per segment ``h_seg`` (P, S, 7) [W/(m²·K)]."""
    states = simulate_states(rom, h_seg, plan, inputs, t0)
    return np.asarray(states @ rom.sensors.T)


@dataclass(frozen=True)
class Tangents:
    """One candidate's run and its exact derivatives: ``sensors`` (n_steps+1, 32) [°C], ``d_sensors``
    (J, n_steps+1, 32) [°C per unit of each direction], ``states`` (n_steps+1, r)."""

    sensors: Array
    d_sensors: Array
    states: Array


def simulate_tangents(
    rom: Any,
    h_seg: ArrayLike,
    dh_seg: ArrayLike,
    plan: SegmentPlan,
    inputs: Any,
    t0: float | ArrayLike,
    *,
    run: tuple[Array, Operators] | None = None,
) -> Tangents:
    """Sensors for one H per segment ``h_seg`` (S, 7) and their derivatives along J directions ``dh_seg``
    (J, S, 7) of H (tangent-linear model of the discrete step, exact to round-off).

    Differentiating a⁺ = A_s·a + G_s·z gives δa⁺ = A_s·δa + δA_s·a + δG_s·z + G_s·δz, with δA_s·a =
    Φ·(L_μ ∘ Φᵀ·δK_s·Φ)·Φᵀ·a and likewise δG_s (``loewner``): the J tangents reuse the candidate's S
    eigendecompositions, so a full Jacobian costs about two runs instead of J + 1. ``run``: the caller's
    ``simulate_run`` of the same H (one candidate), inputs and start, not recomputed.
    """
    h = _check_h(np.asarray(h_seg, dtype=np.float64)[None], plan)
    dh = np.asarray(dh_seg, dtype=np.float64)
    if dh.ndim != 3 or dh.shape[1:] != (plan.n_segments, 7) or not np.all(np.isfinite(dh)):
        raise SegmentError(f"dh_seg: expected finite (J, {plan.n_segments}, 7), got shape {dh.shape}")
    _, amb, qf, qr = _inputs(inputs, plan.n_steps)
    r = rom.k0.shape[0]
    all_states, ops = _run(rom, h, plan, inputs, t0) if run is None else run
    if all_states.shape != (1, plan.n_steps + 1, r) or ops.phi.shape[:2] != (1, plan.n_segments):
        raise SegmentError(
            f"run: expected one candidate's states (1, {plan.n_steps + 1}, {r}) and operators, got "
            f"{all_states.shape}"
        )
    states = all_states[0]  # (n+1, r)
    n_dir = dh.shape[0]
    d_sensors = np.zeros((n_dir, plan.n_steps + 1, rom.sensors.shape[0]))
    d_end = np.zeros((n_dir, r))  # δa at the segment's start (none at the window's start)
    ends = np.append(plan.start[1:], plan.n_steps)
    for s, (k0, k1) in enumerate(zip(plan.start.tolist(), ends.tolist(), strict=True)):
        # the tangents in the segment's modes: β = Φᵀ·δa steps as β⁺ = μ∘β + Φᵀ·(δA·a + δG·z + G·δz)
        phi = ops.phi[0, s]
        y = np.zeros((k1 - k0 + 1, n_dir, r))
        y[0] = d_end @ phi
        # only the directions that move this segment's H (a tabulated family: 2 nodes per zone of 8)
        act = np.flatnonzero(np.any(dh[:, s] != 0.0, axis=1))
        if act.size:
            load = amb[k0:k1, None] * (h[0, s] @ rom.z_zone) + qf[k0:k1, None] * rom.q_front
            load += qr[k0:k1, None] * rom.q_rear  # (n_s, r): z_k
            dk = (dh[act, s] @ rom.k_zone.reshape(7, r * r)).reshape(-1, r, r)  # (J', r, r): δK_s
            d_modal = phi.T @ dk @ phi  # Φᵀ·δK·Φ
            b, c = states[k0:k1] @ phi, load @ phi  # (n_s, r) modal state and load
            src = b @ np.swapaxes(ops.l_mu[0, s] * d_modal, 1, 2) + c @ np.swapaxes(
                ops.l_gamma[0, s] * d_modal, 1, 2
            )  # (J', n_s, r): Φᵀ·(δA·a + δG·z)
            dz = (dh[act, s] @ rom.z_zone) @ phi * ops.gamma[0, s]  # (J', r): Φᵀ·G·δz per °C ambient
            src += amb[None, k0:k1, None] * dz[:, None, :]
            y[1:, act] = np.swapaxes(src, 0, 1)
        rom_modal.blocked_recursion(y, np.broadcast_to(ops.mu[0, s], (n_dir, r)))
        d_sensors[:, k0 + 1 : k1 + 1] = np.swapaxes(y[1:], 0, 1) @ (rom.sensors @ phi).T
        d_end = y[-1] @ phi.T
    return Tangents(
        sensors=np.asarray(states @ rom.sensors.T),
        d_sensors=d_sensors,
        states=states,
    )


def fe_sensors(
    fe: Any, h_seg: ArrayLike, plan: SegmentPlan, inputs: Any, t0: float | ArrayLike, *, theta: float = 1.0
) -> tuple[Array, Array]:
    """Reference: the full FE model (``model.fem``) with K(H_s) switched at each segment start, the field
    carried over. Returns sensors (n_steps+1, 32) [°C] and the final field (N,)."""
    from model.fem import simulate_sensors as fe_simulate

    h = _check_h(np.asarray(h_seg, dtype=np.float64)[None], plan)[0]
    ends = np.append(plan.start[1:], plan.n_steps)
    field: float | Array = np.asarray(t0, dtype=np.float64) if np.ndim(t0) else float(np.asarray(t0))
    parts = []
    for s, (k0, k1) in enumerate(zip(plan.start.tolist(), ends.tolist(), strict=True)):
        sens, field = fe_simulate(fe, h[s], inputs.slice(k0, k1), field, theta=theta)
        parts.append(sens if s == 0 else sens[1:])
    return np.vstack(parts), np.asarray(field)
