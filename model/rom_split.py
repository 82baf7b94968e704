"""Spectral split of the reduced model: slow modes exact, the fast ones quasi-static plus their transients.

The reduced conductance K_r(H) has eigenvalues λ spanning λΔt ≈ 0–14 at Δt = 10 s, and one batched 56 × 56
``eigh`` per candidate was two thirds of an evaluation (docs/design/rom.md, "Evaluation cost"). The top of the
spectrum hardly moves with H over the box, so the split is fixed, independent of H: the eigenbasis Ψ of K_r
at the box centre, its first ``n_slow`` vectors slow (s; by default at the first gap of that spectrum,
``choose_split``: 33 of 56 for the service's model), the rest fast (f). Per candidate, in Ψ:

- slow part: the fast coordinates condensed statically (Schur complement K_red = K_ss − K_sf·K_ff⁻¹·K_fs, load
  z_red = z_s − K_sf·K_ff⁻¹·z_f); its eigenpairs (λ_s, φ) exact (an n_slow × n_slow ``eigh``) and the exact
  modal recursion of ``model.rom_modal`` on them;
- fast part, a_f = h + lag + transient: the quasi-static value h = K_ff⁻¹·(z_f − K_fs·a_s) (exact); its
  first-order lag behind the moving slow state, K_ff⁻¹·W_s·ȧ_s (W_s = K_ff⁻¹·K_fs); and the transient that a
  start field or an input step Δu leaves, decaying along the centre basis at the candidate's diagonal of
  K_ff (no eigensolver for the fast block: K_ff is nearly diagonal in Ψ over the whole box), kept for
  ``n_transient`` steps;
- the transient's pull on the slow modes, to first order in K_sf (the Sylvester solution
  X_jk = (φᵀ·K_sf)_jk / (λ_f,k − λ_s,j)): a jump of the slow state at the start and at every input step.

The jumps and the lag are linear in the inputs and their steps, so they become a modified slow load, a
modified start and an output term: one product of the lagged inputs [u(n−1), Δu(n−1) … Δu(n−K)] with
per-candidate weights. y(0) is the exact projection of the start. Only for the exact per-step solution
(``substeps`` 0): with backward Euler at 10 s the fast modes do not die out within a step.

What it costs in accuracy (≤ 0.003 °C off the exact modal evaluation, no change of the error against a
converged full FE) and what it saves: docs/design/rom.md, "Spectral split". Pure numpy; no I/O.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from model import rom_modal, rom_stream

Array = NDArray[np.float64]

# guards of the split (SplitOperators.usable): the served model has λΔt 1.22 / 1.52 at the centre across
# its split (ratio 1.25) and the 8 transient steps leave exp(−1.5·8) < 1e-5 of a fast transient
MIN_GAP_RATIO = 1.1
MIN_FAST_DECAY = 1.0
AUTO = -1  # n_slow: the first gap of the centre spectrum (choose_split)
AUTO_GAP_RATIO = 1.15  # λ_k / λ_k−1 at the chosen split
AUTO_MIN_RATE = 0.12  # 1/s: the fast modes' floor (λΔt ≥ 1.2 at the service's 10-s step)
DEFAULT_N_TRANSIENT = 8  # steps a fast transient is kept: exp(−1.5·8) < 1e-5 at the default split


@dataclass(frozen=True)
class SplitOperators:
    """The reduced operators in the centre eigenbasis ``psi`` (r, r): k0 (r, r), k_zone (7, r, r),
    z_zone (7, r), q_front and q_rear (r,), sensors (m, r); the first ``n_slow`` coordinates are slow."""

    psi: Array
    k0: Array
    k_zone: Array
    z_zone: Array
    q_front: Array
    q_rear: Array
    sensors: Array
    n_slow: int
    n_transient: int = DEFAULT_N_TRANSIENT
    centre_lam: Array | None = None  # eigenvalues of K_r at the box centre [1/s], ascending

    def usable(self, dt_s: float) -> bool:
        """Whether the split is safe for steps of ``dt_s`` [s]: a gap in the centre spectrum at the split
        (λ_s+1 ≥ ``MIN_GAP_RATIO``·λ_s) and fast modes that die out within the kept transient steps
        (λ_s+1·Δt ≥ ``MIN_FAST_DECAY``). Otherwise the model falls back to the all-exact evaluation."""
        if self.centre_lam is None:
            return True
        slow, fast = float(self.centre_lam[self.n_slow - 1]), float(self.centre_lam[self.n_slow])
        return fast >= MIN_GAP_RATIO * slow and fast * dt_s >= MIN_FAST_DECAY


def split_operators(
    k0: Array,
    k_zone: Array,
    z_zone: Array,
    q_front: Array,
    q_rear: Array,
    sensors: Array,
    *,
    h_centre: Array,
    n_slow: int,
    n_transient: int = DEFAULT_N_TRANSIENT,
) -> SplitOperators | None:
    """Rotate the reduced operators into the eigenbasis of K_r(``h_centre``) (7,), eigenvalues ascending.
    ``n_slow`` ``AUTO``: the split ``choose_split`` finds in that spectrum (None if it finds none)."""
    r = k0.shape[0]
    if not (0 < n_slow < r or n_slow == AUTO):
        raise ValueError(f"n_slow: expected 0 < n_slow < rank {r} or {AUTO} (auto), got {n_slow}")
    if n_transient < 0:
        raise ValueError(f"n_transient: expected >= 0, got {n_transient}")
    centre = np.asarray(h_centre, dtype=np.float64)[None, :]
    lam, psi = np.linalg.eigh(rom_modal.conductance(k0, k_zone, centre))
    psi = psi[0]
    if n_slow == AUTO:
        n_slow = choose_split(lam[0])
        if n_slow == 0:
            return None
    return SplitOperators(
        psi=psi,
        k0=psi.T @ k0 @ psi,
        k_zone=np.einsum("ri,zrs,sj->zij", psi, k_zone, psi),
        z_zone=z_zone @ psi,
        q_front=psi.T @ q_front,
        q_rear=psi.T @ q_rear,
        sensors=sensors @ psi,
        n_slow=n_slow,
        n_transient=n_transient,
        centre_lam=lam[0],
    )


def choose_split(centre_lam: Array) -> int:
    """The number of slow modes: the first k ≥ r/2 with λ_k ≥ ``AUTO_GAP_RATIO``·λ_k−1 and λ_k ≥
    ``AUTO_MIN_RATE`` in the ascending centre spectrum [1/s] (33 for the service's default model, whose gap
    holds over the whole box: docs/design/rom.md, "Spectral split"); 0 if there is none."""
    lam = np.asarray(centre_lam, dtype=np.float64)
    for k in range(max(1, lam.size // 2), lam.size):
        if lam[k] >= AUTO_GAP_RATIO * lam[k - 1] and lam[k] >= AUTO_MIN_RATE:
            return k
    return 0


@dataclass(frozen=True)
class SplitRun:
    """One population's window: ``run`` the slow modes (``model.rom_modal.ModalRun``), ``gain`` (P, m, s)
    their outputs, ``direct`` (P, 3 + 3K, m) the weights of ``lagged_inputs``, ``start`` (P, K, m) the start
    transient at steps 1..K and ``y0`` (P, m) the outputs at step 0."""

    run: rom_modal.ModalRun
    gain: Array
    direct: Array
    start: Array
    y0: Array


def step_inputs(segments: rom_modal.Segments) -> Array:
    """Per-step inputs (n_steps, 3): ambient [°C], front and rear bearing heat [W]."""
    return np.repeat(rom_modal.segment_inputs(segments), segments.length, axis=0)


def lagged_inputs(u: Array, n_transient: int) -> Array:
    """Rows n = 0..n_steps−1 (the output of step n+1): [u(n), Δu(n), Δu(n−1) … Δu(n−K+1)] with Δu(k) =
    u(k) − u(k−1) for k ≥ 1 and 0 before step 1, shape (n_steps, 3 + 3K)."""
    n = u.shape[0]
    du = np.zeros_like(u)
    du[1:] = u[1:] - u[:-1]
    out = np.zeros((n, 3 + 3 * n_transient))
    out[:, :3] = u
    for k in range(1, n_transient + 1):
        if n > k:
            out[k:, 3 * k : 3 * k + 3] = du[1 : n - k + 1]
    return out


def split_run(
    ops: SplitOperators, h: Array, segments: rom_modal.Segments, a0: Array, scale: Array, dt_s: float
) -> SplitRun:
    """The window for P candidates H (P, 7) from the reduced start ``a0`` (P, r) (the model's own basis), with
    the heat loads times ``scale`` (P, 2); exact per-step solution of the slow modes (``substeps`` 0)."""
    s = ops.n_slow
    p, r = h.shape[0], ops.k0.shape[0]
    k = rom_modal.conductance(ops.k0, ops.k_zone, h)
    ksf, kff = k[:, :s, s:], k[:, s:, s:]
    loads = np.empty((p, r, 3))
    loads[:, :, 0] = h @ ops.z_zone
    loads[:, :, 1] = ops.q_front[None, :] * scale[:, 0:1]
    loads[:, :, 2] = ops.q_rear[None, :] * scale[:, 1:2]
    kinv = np.linalg.inv(kff)
    w = np.matmul(kinv, np.concatenate([k[:, s:, :s], loads[:, s:, :]], axis=2))  # K_ff⁻¹·[K_fs | z_f]
    # the fast transients decay along the centre basis with the candidate's diagonal of K_ff as rates
    lam_f = np.diagonal(kff, axis1=1, axis2=2).copy()
    ws, wz = w[:, :, :s], w[:, :, s:]
    kinv_ws = np.matmul(kinv, ws)
    kred = k[:, :s, :s] - np.matmul(ksf, ws)
    zred = loads[:, :s, :] - np.matmul(ksf, wz)
    lam, phi = np.linalg.eigh(kred)
    phi_t = np.swapaxes(phi, 1, 2)
    c_s, c_f = ops.sensors[:, :s], ops.sensors[:, s:]
    lag_gain = np.matmul(c_f, kinv_ws)  # outputs per unit ȧ_s through the fast lag
    gain = np.matmul(c_s - np.matmul(c_f, ws), phi) - np.matmul(lag_gain, phi) * lam[:, None, :]
    feed = np.matmul(c_f, wz) + np.matmul(lag_gain, zred)  # (P, m, 3) per u(n−1)
    coupling = np.matmul(phi_t, ksf)  # (P, s, f)
    gap = lam_f[:, None, :] - lam[:, :, None]
    x = coupling / np.maximum(gap, 0.1 * lam_f[:, None, :])  # Sylvester, guarded against a closed gap
    c_trans = c_f + np.matmul(gain, x)  # (P, m, f)
    per_jump = -wz - np.matmul(kinv_ws, zred)  # fast transient per unit Δu (P, f, 3)
    jump = -np.matmul(x, per_jump)  # slow-state jump per unit Δu (P, s, 3)
    # start: the transient of the start field and its pull on the slow modes
    u = step_inputs(segments)
    u0 = u[0] if u.shape[0] else np.zeros(3)
    a0c = (np.broadcast_to(a0, (p, r)) @ ops.psi)[:, :, None]  # (P, r, 1)
    a0s = a0c[:, :s]
    u0c = np.broadcast_to(u0[:, None], (p, 3, 1))
    slope = np.matmul(zred, u0c) - np.matmul(kred, a0s)
    tau0 = a0c[:, s:] - np.matmul(wz, u0c) + np.matmul(ws, a0s) - np.matmul(kinv_ws, slope)
    b0 = np.matmul(phi_t, a0s) - np.matmul(x, tau0) - np.matmul(jump, u0c)
    forcing = np.matmul(phi_t, zred) - lam[:, :, None] * jump  # slow load with the jumps folded in
    n_tr = ops.n_transient
    decay = np.exp(-lam_f[:, :, None] * (dt_s * np.arange(1, n_tr + 1)))  # (P, f, K)
    direct = np.empty((p, 3 + 3 * n_tr, c_s.shape[0]))
    direct[:, :3, :] = np.swapaxes(feed + np.matmul(gain, jump), 1, 2)
    kern = (decay[:, :, :, None] * per_jump[:, :, None, :]).reshape(p, -1, 3 * n_tr)  # (P, f, K·3)
    direct[:, 3:, :] = np.swapaxes(np.matmul(c_trans, kern), 1, 2)
    start = np.swapaxes(np.matmul(c_trans, decay * tau0), 1, 2)  # (P, K, m)
    b0 = b0[:, :, 0]
    mu, _ = rom_modal.step_factors(lam, dt_s, 1.0, 0)
    run = rom_modal.ModalRun(
        b0, lam, mu, (forcing[:, :, 0], forcing[:, :, 1], forcing[:, :, 2]), segments, np.ones((p, 2))
    )
    return SplitRun(run=run, gain=gain, direct=direct, start=start, y0=(ops.sensors @ a0c)[:, :, 0])


def window_outputs(sr: SplitRun, segments: rom_modal.Segments) -> Array:
    """Outputs (P, n_steps+1, m): the slow modes (``model.rom_stream`` for a wide population, else the
    trajectory), the fast part's direct term, the start transient and the exact step 0."""
    n = int(segments.length.sum())
    lagged = lagged_inputs(step_inputs(segments), sr.start.shape[1])
    y = rom_stream.window_outputs(sr.run, sr.gain, direct=(lagged, sr.direct))
    k = min(sr.start.shape[1], n)
    y[:, 1 : k + 1, :] += sr.start[:, :k, :]
    y[:, 0, :] = sr.y0
    return np.asarray(y)
