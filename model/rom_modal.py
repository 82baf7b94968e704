"""Closed-form modal solution of the reduced θ-method for a population of H candidates.

The reduced system has an E-orthonormal basis, so the reduced heat capacity is the identity and, for one
candidate H, the reduced conductance K_r(H) = K0_r + Σ H_i·K_i,r is symmetric positive definite. With
K_r = Φ·diag(λ)·Φᵀ the θ-method step

    (I/Δt + θ·K_r)·a(n+1) = (I/Δt − (1−θ)·K_r)·a(n) + z_r(n)

decouples into scalar recursions b_j(n+1) = μ_j·b_j(n) + γ_j·c_j(n) with b = Φᵀa, c = Φᵀz_r,
μ_j = (1/Δt − (1−θ)·λ_j)/(1/Δt + θ·λ_j) and γ_j = 1/(1/Δt + θ·λ_j). On a segment of constant input the fixed
point is b* = c/λ and b(n0+k) = b* + μ^k·(b(n0) − b*): this is the exact discrete θ-method trajectory (not an
exponential-integrator approximation), evaluated with one eigen-decomposition per candidate and one power
table per window.

Pure numpy; no I/O. All arrays are float64.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]


@dataclass(frozen=True)
class Segments:
    """Runs of constant input: ``start[s]`` (step index), ``length[s]`` (steps) and the input values."""

    start: NDArray[np.int64]
    length: NDArray[np.int64]
    ambient_c: Array
    q_front_w: Array
    q_rear_w: Array


def split_segments(ambient_c: Array, q_front_w: Array, q_rear_w: Array) -> Segments:
    """Split per-step inputs (°C, W, W; length n_steps) into runs where all three stay constant."""
    stacked = np.stack([ambient_c, q_front_w, q_rear_w]).astype(np.float64)
    n_steps = stacked.shape[1]
    if n_steps == 0:
        empty_i = np.zeros(0, dtype=np.int64)
        empty_f = np.zeros(0)
        return Segments(empty_i, empty_i, empty_f, empty_f, empty_f)
    change = np.flatnonzero(np.any(np.diff(stacked, axis=1) != 0.0, axis=0)) + 1
    start = np.concatenate([[0], change]).astype(np.int64)
    length = np.diff(np.concatenate([start, [n_steps]])).astype(np.int64)
    return Segments(start, length, stacked[0, start], stacked[1, start], stacked[2, start])


def conductance(k0: Array, k_zone: Array, h: Array) -> Array:
    """Reduced conductance K_r(H) (P, r, r) [W/K] for H (P, 7) [W/(m²·K)]."""
    r = k0.shape[0]
    kr = (h @ k_zone.reshape(k_zone.shape[0], r * r)).reshape(h.shape[0], r, r)
    kr += k0[None, :, :]
    return kr


def ambient_load(z_zone: Array, h: Array) -> Array:
    """Reduced ambient load vector Σ H_i·z_i,r (P, r) [W/K], multiplied by T_ambient at run time."""
    return h @ z_zone


@dataclass(frozen=True)
class Modes:
    """Eigen-decomposition of K_r(H) for P candidates: ``lam`` (P, r) [W/K], ``phi`` (P, r, r)."""

    lam: Array
    phi: Array


def modes(k0: Array, k_zone: Array, h: Array) -> Modes:
    """Eigenpairs of the symmetric reduced conductance for every candidate (batched LAPACK ``syevd``)."""
    lam, phi = np.linalg.eigh(conductance(k0, k_zone, h))  # LAPACK reads the lower triangle only
    return Modes(lam=lam, phi=phi)


def step_factors(lam: Array, dt_s: float, theta: float, substeps: int = 1) -> tuple[Array, Array]:
    """Amplification μ over one input step of ``dt_s`` [s] and input gain γ = (1 − μ)/λ per mode (same shape
    as ``lam``).

    ``substeps`` s ≥ 1: s θ-method steps of Δt/s with the input held, μ = μ_θ(Δt/s)^s (s = 1: the plain
    θ-method, γ = 1/(1/Δt + θλ)). ``substeps`` 0: the exact solution of the reduced ODE with the input held
    over the step (zero-order hold), μ = exp(−λΔt) — the limit s → ∞, free of time-step error.
    """
    if substeps == 0:
        mu = np.exp(-lam * dt_s)
    else:
        h = dt_s / substeps
        mu = ((1.0 / h - (1.0 - theta) * lam) / (1.0 / h + theta * lam)) ** substeps
    with np.errstate(divide="ignore", invalid="ignore"):
        gamma = np.where(lam > 0.0, (1.0 - mu) / np.where(lam > 0.0, lam, 1.0), dt_s)
    return mu, gamma


def power_table(mu: Array, n_max: int) -> Array:
    """μ^k for k = 0..n_max, shape (n_max+1, P, r) (cumulative product: exact powers, also for μ < 0)."""
    p, r = mu.shape
    table = np.empty((n_max + 1, p, r))
    table[0] = 1.0
    if n_max > 0:
        np.cumprod(np.broadcast_to(mu, (n_max, p, r)), axis=0, out=table[1:])
    return table


@dataclass(frozen=True)
class ModalRun:
    """One population's reduced θ-method window in modal coordinates.

    ``b0`` start b(0), ``lam`` eigenvalues λ [1/s] and ``mu`` step amplification μ, each (P, r); ``forcing`` =
    (u_ambient, u_front, u_rear), each (P, r): modal loads per 1 °C of ambient and per 1 W of front/rear
    bearing heat; the input ``segments``; ``load_scale`` (P, 2) multiplies the heat loads per candidate.
    """

    b0: Array
    lam: Array
    mu: Array
    forcing: tuple[Array, Array, Array]
    segments: Segments
    load_scale: Array


def modal_trajectory(run: ModalRun, *, method: str = "auto") -> Array:
    """Modal coordinates b(n), time-major (n_steps+1, P, r), from b(0) (P, r).

    A segment of one step costs one multiply-add (b⁺ = μ·b + γ·c); a longer one uses the power table in one
    vectorised block, so the cost is ~(number of segments) small operations plus one pass over the output.
    ``method`` "blocked" (``blocked_recursion``, ~4√n larger operations: better for one or two candidates and
    inputs that change every step) or "scan" (``linear_scan``) replace the loop; "auto" picks by
    ``choose_method``.
    """
    if method not in ("auto", "loop", "scan", "blocked"):
        raise ValueError(f"method: expected 'auto', 'loop', 'scan' or 'blocked', got {method!r}")
    segments, mu = run.segments, run.mu
    n_steps = int(segments.length.sum())
    p, r = run.b0.shape
    out = np.empty((n_steps + 1, p, r))
    out[0] = run.b0
    if n_steps == 0:
        return out
    fixed_op, step_op = unit_responses(run)
    x = segment_inputs(segments)
    increment = (x @ step_op).reshape(-1, p, r)  # one BLAS product for all segments
    if method == "auto":
        method = choose_method(segments.start.size, n_steps, p * r)
    if method in ("scan", "blocked"):
        out[1:] = np.repeat(increment, segments.length, axis=0)
        return linear_scan(out, mu) if method == "scan" else blocked_recursion(out, mu)
    long_max = int(segments.length.max())
    pw = power_table(mu, long_max) if long_max > 1 else None
    multiply = np.multiply
    for s, (n0, length) in enumerate(zip(segments.start.tolist(), segments.length.tolist(), strict=True)):
        if length == 1 or pw is None:
            nxt = out[n0 + 1]
            multiply(mu, out[n0], out=nxt)
            nxt += increment[s]
            continue
        fixed = (x[s] @ fixed_op).reshape(p, r)
        block = out[n0 + 1 : n0 + length + 1]
        multiply(pw[1 : length + 1], out[n0] - fixed, out=block)
        block += fixed
    return out


def unit_responses(run: ModalRun) -> tuple[Array, Array]:
    """Per unit input (rows: 1 °C ambient, 1 W front, 1 W rear) the fixed point b* = c/λ and the step
    increment γ·c = (1−μ)·c/λ, each (3, P·r), so that ``inputs (S, 3) @ op`` gives all segments at once
    (heat loads times the run's ``load_scale``)."""
    forcing, scale, lam = run.forcing, run.load_scale, run.lam
    p, r = lam.shape
    u = np.stack([forcing[0], forcing[1] * scale[:, 0:1], forcing[2] * scale[:, 1:2]])  # (3, P, r)
    to_fixed = u / lam[None, :, :]
    return to_fixed.reshape(3, p * r), (to_fixed * (1.0 - run.mu)[None, :, :]).reshape(3, p * r)


def segment_inputs(segments: Segments) -> Array:
    """The segments' inputs as rows (S, 3): ambient [°C], front and rear bearing heat [W]."""
    return np.stack([segments.ambient_c, segments.q_front_w, segments.q_rear_w], axis=1)


def choose_method(n_segments: int, n_steps: int, width: int) -> str:
    """ "loop" for few segments or a wide population (P·r > 128), else "blocked".

    Measured on 2 cores, r = 50, 360 steps with inputs changing every step: P = 1–2 blocked 0.5–0.9 ms vs
    loop 1.1–1.5 ms; P ≥ 4 the loop wins (1.5 vs 1.7 ms at P = 4, 9 vs 18 ms at P = 28); the scan is never
    best there (kept for tests and small dense problems).
    """
    if n_segments <= 2 * np.sqrt(n_steps) or width > 128:
        return "loop"
    return "blocked"


def blocked_recursion(y: Array, mu: Array) -> Array:
    """In place, same result as ``linear_scan``: y[n] ← Σ_{m≤n} μ^(n−m)·y[m] along axis 0, in blocks of
    ~√n steps: the recursion runs inside all blocks at once (√n vectorised passes), then once across the
    block starts (√n small passes), then one vectorised fill. ~4√n numpy calls instead of 2n."""
    n = y.shape[0] - 1
    if n <= 0:
        return y
    size = int(np.ceil(np.sqrt(n)))
    n_blocks = -(-n // size)
    inc = np.zeros((n_blocks * size, *y.shape[1:]))
    inc[:n] = y[1:]
    inc = inc.reshape((n_blocks, size, *y.shape[1:]))
    acc = np.zeros((n_blocks, *y.shape[1:]))
    for k in range(size):  # partial sums inside every block: Σ_{j≤k} μ^(k−j)·inc[j]
        acc *= mu
        acc += inc[:, k]
        inc[:, k] = acc
    pw = power_table(mu, size)
    starts = np.empty((n_blocks, *y.shape[1:]))
    current = y[0]
    for c in range(n_blocks):
        starts[c] = current
        current = pw[size] * current + inc[c, size - 1]
    full = pw[None, 1:] * starts[:, None] + inc
    y[1:] = full.reshape((n_blocks * size, *y.shape[1:]))[:n]
    return y


def linear_scan(y: Array, mu: Array) -> Array:
    """In place: y[n] ← Σ_{m≤n} μ^(n−m)·y[m] along axis 0 (Hillis–Steele doubling, log2(n) passes).

    With y[0] = b(0) and y[k+1] = the increment of step k this is the θ-method trajectory b(n).
    """
    shift, power = 1, mu.copy()
    while shift < y.shape[0]:
        y[shift:] += power * y[:-shift]
        shift, power = 2 * shift, power * power
    return y
