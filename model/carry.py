"""Carrying the start field's uncertainty through an identification window (linearised, pure).

A service starts each window from its live state, which earlier windows' H made; their errors are in that
start field and bias the new H. Ignoring them gives CIs that only know the window's own noise. Here the
error of the reduced start state a₀ (``model.rom``: T ≈ V·a) is a zero-mean Gaussian with covariance P₀
(r, r) [°C²], written P₀ = U·Uᵀ (``factor``). To first order, around the fitted θ̂:

- each start direction u_j moves the model's sensor values by R_j = C·Φ·diag(μᵏ)·Φᵀ·u_j (exact: the reduced
  model is linear in a₀ for fixed θ), and the least-squares fit answers with δθ_j = −(JᵀJ)⁺·Jᵀ·R_j, the
  columns of the gain G (p, k);
- the parameters' covariance is σ²(JᵀJ)⁺ + G·Gᵀ (the window's noise plus the carried start error);
- the window-end state's error is (E·U + S·G)·z + S·δθ_noise, with E = Φ·diag(μⁿ)·Φᵀ the window's
  homogeneous propagator and S = ∂a_end/∂θ, so its covariance is
  P_end = (E·U + S·G)(E·U + S·G)ᵀ + S·C_fit·Sᵀ: the next window's P₀ after ``propagate`` over the gap.

Simplifications (docs/identification.md, "Start-field uncertainty"): linear about θ̂; the field's error outside
the reduced basis and the live state's FE-vs-ROM difference are ignored; between a window's end and the next
window's start the error only decays (the gap's own H error is not added).

Errors::

    CarryError(ValueError)   a covariance of the wrong shape or not finite (the argument is named)
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from model import rom_modal

Array = NDArray[np.float64]
N_H = 7


class CarryError(ValueError):
    """A start covariance of the wrong shape or with non-finite entries."""


@dataclass(frozen=True, eq=False)
class StateCovariance:
    """The live state's error covariance ``cov`` (r, r) [°C², reduced coordinates] at ``t_s`` [s]; after
    ``t_s`` the state evolved under ``h`` (7,) [W/(m²·K)]."""

    t_s: float
    cov: Array
    h: Array


@dataclass(frozen=True, eq=False)
class Carried:
    """What a window makes of its start uncertainty: θ's total covariance, the gain and the end covariance."""

    cov: Array  # (p, p) σ²(JᵀJ)⁺ + G·Gᵀ
    gain: Array  # (p, k) δθ per unit start coefficient
    end_cov: Array  # (r, r) [°C²] of the reduced state at the window end


def check_cov(cov: Any, r: int, name: str = "start_cov") -> Array:
    """The covariance as an (r, r) symmetric float array; ``CarryError`` names ``name`` otherwise."""
    arr = np.asarray(cov, dtype=np.float64)
    if arr.shape != (r, r) or not np.all(np.isfinite(arr)):
        raise CarryError(f"{name}: expected a finite ({r}, {r}) covariance, got shape {arr.shape}")
    return 0.5 * (arr + arr.T)


def factor(cov: Array, *, rtol: float = 1e-10) -> Array:
    """U (r, k) with U·Uᵀ = cov, dropping eigenvalues below ``rtol``·max (k = 0 for a zero covariance)."""
    lam, vec = np.linalg.eigh(cov)
    top = float(lam.max(initial=0.0))
    keep = lam > rtol * top if top > 0.0 else np.zeros(lam.shape, dtype=bool)
    return np.asarray(vec[:, keep] * np.sqrt(lam[keep])[None, :])


def _modes(rom: Any, h: Array, dt_s: float) -> tuple[Array, Array]:
    md = rom_modal.modes(rom.k0, rom.k_zone, np.asarray(h, dtype=np.float64).reshape(1, N_H))
    mu, _ = rom_modal.step_factors(md.lam, float(dt_s), float(rom.theta))
    return np.asarray(md.phi[0]), np.asarray(mu[0])


def propagator(rom: Any, h: Array, dt_s: float, n_steps: int) -> Array:
    """E (r, r): the reduced state's homogeneous evolution over ``n_steps`` steps of ``dt_s`` under H."""
    phi, mu = _modes(rom, h, dt_s)
    return np.asarray((phi * mu[None, :] ** max(int(n_steps), 0)) @ phi.T)


def propagate(rom: Any, sc: StateCovariance, t_s: float, dt_s: float) -> Array:
    """``sc.cov`` decayed from ``sc.t_s`` to ``t_s`` [s] under ``sc.h`` (a no-op when ``t_s <= sc.t_s``)."""
    n = round((float(t_s) - sc.t_s) / float(dt_s))
    cov = check_cov(sc.cov, int(rom.k0.shape[0]), "state covariance")
    if n <= 0:
        return cov
    e = propagator(rom, sc.h, dt_s, n)
    return np.asarray(e @ cov @ e.T)


def start_responses(rom: Any, h: Array, dt_s: float, n_steps: int, u: Array) -> Array:
    """Sensor responses (k, n_steps + 1, 32) [°C] to the start directions ``u`` (r, k) under H."""
    phi, mu = _modes(rom, h, dt_s)
    gain = np.asarray(rom.sensors) @ phi  # (32, r)
    powers = mu[None, :] ** np.arange(n_steps + 1)[:, None]  # (n+1, r)
    coeff = phi.T @ u  # (r, k)
    return np.asarray(np.einsum("sr,nr,rk->kns", gain, powers, coeff))


def end_jacobian(problem: Any, theta: Array, *, rel_step: float = 1e-6) -> Array:
    """S (r, p) = ∂a_end/∂θ by forward differences of the reduced trajectory (``problem``: an
    ``identify_problem.Problem`` over a ``ReducedModel``)."""
    x = np.asarray(theta, dtype=np.float64)
    step = rel_step * np.maximum(np.abs(x), 1.0)
    step = np.where(x + step > problem.bounds[:, 1], -step, step)
    base = end_state(problem, x)
    cols = [(end_state(problem, x + step[i] * np.eye(len(x))[i]) - base) / step[i] for i in range(len(x))]
    return np.asarray(np.column_stack(cols))


def end_state(problem: Any, theta: Array) -> Array:
    """The reduced state (r,) at the window end for parameters θ (p,)."""
    lay = problem.layout
    loads, shift = lay.load_scale(theta), lay.shift(theta)
    t0 = problem.t0 if shift is None else np.asarray(problem.t0, dtype=np.float64) + float(shift)
    traj = problem.model.simulate_state(
        theta[:N_H], problem.inputs, t0, load_scale=None if loads is None else np.asarray(loads)
    )
    return np.asarray(traj[-1])


def carry(problem: Any, theta: Array, jac: Array, fit_cov: Array, start_cov: Array) -> Carried:
    """θ's total covariance and the window-end state covariance, given P₀ = ``start_cov`` (r, r) [°C²].

    ``jac`` (m, p) is the residuals' Jacobian at θ̂ over the usable entries, ``fit_cov`` (p, p) = σ²(JᵀJ)⁺.
    """
    rom = problem.model
    r = int(rom.k0.shape[0])
    p0 = check_cov(start_cov, r)
    u = factor(p0)
    dt, n = float(problem.inputs.dt_s), len(problem.inputs.ambient_c)
    h = np.asarray(theta[:N_H], dtype=np.float64)
    resp = problem.select(start_responses(rom, h, dt, n, u))  # (k, m)
    gain = -np.linalg.pinv(jac.T @ jac) @ (jac.T @ resp.T)  # (p, k)
    s = end_jacobian(problem, theta)
    moved = propagator(rom, h, dt, n) @ u + s @ gain  # (r, k)
    end_cov = moved @ moved.T + s @ fit_cov @ s.T
    total = fit_cov + gain @ gain.T
    return Carried(0.5 * (total + total.T), gain, 0.5 * (end_cov + end_cov.T))
