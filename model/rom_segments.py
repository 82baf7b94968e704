"""The reduced model over a window whose H change from segment to segment, for a population of candidates.

``model.rom.ReducedModel`` evaluates one H per candidate over a whole window. A window with speed changes
has H_s for segment s (S segments): K_r(H_s) = K0_r + Σ H_s,i·K_i,r switches at each segment start while the
reduced state carries over (the state is continuous; only the operator changes, as in the full FE with a
time-varying K(H)). This module steps the reduced θ-method directly::

    (I/Δt + θ·K_s)·a(k+1) = (I/Δt − (1−θ)·K_s)·a(k) + z_k,   z_k = Ti_k·Σ H_s,i·z_i + Qf_k·q_f + Qr_k·q_r

with one inverse of I/Δt + θ·K_s per (candidate, segment) (batched LAPACK), the per-step loads mapped by it
in one product per segment, and one batched matrix–vector product per step for the whole population. It
reads the public arrays of a ``ReducedModel`` (k0, k_zone, z_zone, q_front, q_rear, sensors, theta,
initial_state, lift) and changes nothing there; with one segment it reproduces ``simulate_sensors`` to
round-off (a test checks it).

Errors::

    SegmentError(ValueError)   bad segment index, H shape or inputs (the argument is named)
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

Array = NDArray[np.float64]


class SegmentError(ValueError):
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


def _operators(rom: Any, h: Array, dt: float) -> tuple[Array, Array]:
    """Per (candidate, segment): the step matrix A = M·(I/Δt − (1−θ)K) and M = (I/Δt + θK)⁻¹, (P, S, r, r)."""
    r = rom.k0.shape[0]
    p, s, _ = h.shape
    k = (h.reshape(p * s, 7) @ rom.k_zone.reshape(7, r * r)).reshape(p, s, r, r) + rom.k0
    eye = np.eye(r) / dt
    theta = float(rom.theta)
    m = np.linalg.inv(eye + theta * k)
    a = m / dt if theta == 1.0 else m @ (eye - (1.0 - theta) * k)
    return a, m


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
    h = _check_h(h_seg, plan)
    dt, amb, qf, qr = _inputs(inputs, plan.n_steps)
    a_op, m_op = _operators(rom, h, dt)
    p = h.shape[0]
    hz = h @ rom.z_zone  # (P, S, r): ambient load per °C
    out = np.empty((p, plan.n_steps + 1, rom.k0.shape[0]))
    out[:, 0] = _start(rom, t0, p)
    w = np.empty((p, plan.n_steps, out.shape[2]))
    ends = np.append(plan.start[1:], plan.n_steps)
    for s, (k0, k1) in enumerate(zip(plan.start.tolist(), ends.tolist(), strict=True)):
        z = (
            amb[None, k0:k1, None] * hz[:, s, None, :]
            + qf[k0:k1, None] * rom.q_front
            + qr[k0:k1, None] * rom.q_rear
        )
        w[:, k0:k1] = z @ np.swapaxes(m_op[:, s], 1, 2)  # M_s·z_k for all steps of the segment
    _recur(out, w, a_op, plan)
    return out


def _recur(out: Array, w: Array, a_op: Array, plan: SegmentPlan) -> None:
    """a(k+1) = A_s(k)·a(k) + w_k in place over all steps (one batched mat-vec per step)."""
    a_t = np.ascontiguousarray(np.swapaxes(a_op, 2, 3))  # row-vector form: a(k+1) = a(k)·A_sᵀ
    seg = plan.of_step.tolist()
    for k in range(plan.n_steps):
        np.matmul(out[:, k, None, :], a_t[:, seg[k]], out=out[:, k + 1, None, :])
        out[:, k + 1] += w[:, k]


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
    rom: Any, h_seg: ArrayLike, dh_seg: ArrayLike, plan: SegmentPlan, inputs: Any, t0: float | ArrayLike
) -> Tangents:
    """Sensors for one H per segment ``h_seg`` (S, 7) and their derivatives along J directions ``dh_seg``
    (J, S, 7) of H (tangent-linear model of the discrete θ-method, exact to round-off).

    Differentiating (I/Δt + θK_s)·a⁺ = (I/Δt − (1−θ)K_s)·a + z gives
    δa⁺ = A_s·δa + M_s·(δz − δK_s·(θa⁺ + (1−θ)a)): the J tangents reuse the candidate's S inverses, so a
    full Jacobian costs about two runs instead of J + 1 (one per finite-difference point).
    """
    h = _check_h(np.asarray(h_seg, dtype=np.float64)[None], plan)
    dh = np.asarray(dh_seg, dtype=np.float64)
    if dh.ndim != 3 or dh.shape[1:] != (plan.n_segments, 7) or not np.all(np.isfinite(dh)):
        raise SegmentError(f"dh_seg: expected finite (J, {plan.n_segments}, 7), got shape {dh.shape}")
    dt, amb, _, _ = _inputs(inputs, plan.n_steps)
    states = simulate_states(rom, h, plan, inputs, t0)[0]  # (n+1, r)
    a_op, m_op = _operators(rom, h, dt)
    theta = float(rom.theta)
    mid = theta * states[1:] + (1.0 - theta) * states[:-1]  # (n, r)
    k_a = np.swapaxes(mid @ np.swapaxes(rom.k_zone, 1, 2), 0, 1)  # (n, 7, r): K_i·(θa⁺ + (1−θ)a)
    dh_step = np.ascontiguousarray(np.swapaxes(dh[:, plan.of_step], 0, 1))  # (n, J, 7)
    src = amb[:, None, None] * (dh_step @ rom.z_zone) - dh_step @ k_a  # (n, J, r)
    src = np.swapaxes(src, 0, 1)
    w = np.empty_like(src)
    ends = np.append(plan.start[1:], plan.n_steps)
    for s, (k0, k1) in enumerate(zip(plan.start.tolist(), ends.tolist(), strict=True)):
        w[:, k0:k1] = src[:, k0:k1] @ m_op[0, s].T
    d_states = np.zeros((1, dh.shape[0], plan.n_steps + 1, states.shape[1]))
    _recur_shared(d_states[0], w, a_op[0], plan)
    return Tangents(
        sensors=np.asarray(states @ rom.sensors.T),
        d_sensors=np.asarray(d_states[0] @ rom.sensors.T),
        states=states,
    )


def _recur_shared(out: Array, w: Array, a_op: Array, plan: SegmentPlan) -> None:
    """Like ``_recur`` for J vectors that share the operators a_op (S, r, r): out (J, n+1, r) in place."""
    a_t = np.ascontiguousarray(np.swapaxes(a_op, 1, 2))
    seg = plan.of_step.tolist()
    for k in range(plan.n_steps):
        np.matmul(out[:, k], a_t[seg[k]], out=out[:, k + 1])
        out[:, k + 1] += w[:, k]


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
