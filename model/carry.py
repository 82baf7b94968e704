"""Carrying the start field's uncertainty through an identification window (pure).

A service starts each window from its live state, which earlier windows' H made; their errors are in that
start field and bias the new H. Ignoring them gives CIs that only know the window's own noise. Here the
error of the reduced start state a₀ (``model.rom``: T ≈ V·a) has covariance P₀ (r, r) [°C²], written
P₀ = U·Uᵀ (``factor``), and around the fitted θ̂:

- each start direction u_j moves the model's sensor values by R_j = C·Φ·diag(μᵏ)·Φᵀ·u_j (exact: the reduced
  model is linear in a₀ for fixed θ), and the least-squares fit answers with δθ_j = −(JᵀJ)⁺·Jᵀ·R_j, the
  columns of the gain G (p, k);
- the parameters' covariance is σ²(JᵀJ)⁺ + G·Gᵀ (the window's noise plus the carried start error);
- the window-end state's error is an ensemble (``end_ensemble``): z ~ N(0, I), ξ ~ N(0, σ²(JᵀJ)⁺),
  θ = θ̂ + G·z + ξ, start a₀ + U·z, each member a full reduced run (not linearised);
- the next window's P₀ comes from running the members through the gap's inputs, each with its own H
  (``propagate``).

Simplifications (docs/design/identification.md, "Start-field uncertainty"): Gaussian in the reduced
coordinates; the field's error outside the reduced basis and the live state's FE-vs-reduced difference are
ignored.

Errors::

    CarryError(ValueError)   a covariance of the wrong shape or not finite (the argument is named)
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from model import rom_modal
from model.errors import ModelError

Array = NDArray[np.float64]
N_H = 7
ENSEMBLE = 128  # members of the end-state ensemble (``end_ensemble``)


class CarryError(ModelError, ValueError):
    """A start covariance of the wrong shape or with non-finite entries."""


@dataclass(frozen=True, eq=False)
class Ensemble:
    """The window-end state's error as an ensemble about the fitted end state ``a_end`` (r,): per member the
    deviation of the state ``dev_a`` (M, r) [°C, reduced] and of θ ``dev_theta`` (M, p), drawn jointly."""

    a_end: Array
    dev_a: Array
    dev_theta: Array

    @property
    def cov(self) -> Array:
        """Second moment (r, r) [°C²] of the state deviations."""
        return np.asarray(self.dev_a.T @ self.dev_a / max(len(self.dev_a), 1))


@dataclass(frozen=True, eq=False)
class StateCovariance:
    """A rebased live state's error at ``t_s`` [s]: the ``ensemble`` of the window that produced it, whose
    state then evolved under ``h`` (7,) [W/(m²·K)] and ``load_scale`` (2,) (θ's first 7 / next 2 entries)."""

    t_s: float
    ensemble: Ensemble
    h: Array
    load_scale: Array | None = None


@dataclass(frozen=True, eq=False)
class Carried:
    """What a window makes of its start uncertainty: θ's total covariance, the gain and the end ensemble."""

    cov: Array  # (p, p) σ²(JᵀJ)⁺ + G·Gᵀ
    gain: Array  # (p, k) δθ per unit start coefficient
    ensemble: Ensemble


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
    mu, _ = rom_modal.step_factors(md.lam, float(dt_s), float(rom.theta), int(getattr(rom, "substeps", 1)))
    return np.asarray(md.phi[0]), np.asarray(mu[0])


def propagator(rom: Any, h: Array, dt_s: float, n_steps: int) -> Array:
    """E (r, r): the reduced state's homogeneous evolution over ``n_steps`` steps of ``dt_s`` under H."""
    phi, mu = _modes(rom, h, dt_s)
    return np.asarray((phi * mu[None, :] ** max(int(n_steps), 0)) @ phi.T)


def propagate(rom: Any, sc: StateCovariance, t_s: float, dt_s: float, gap: Any = None) -> Array:
    """The start covariance (r, r) [°C²] at ``t_s`` [s] of a state rebased at ``sc.t_s``.

    With ``gap`` (the inputs from ``sc.t_s`` to ``t_s``, ``model.inputs.InputSeries``) every ensemble member
    runs through it with its own H and load scales, so the H error keeps acting after the window (that is
    most of the error a short gap adds: the data no longer pin the state). Without, the error only decays
    (``propagator``). A no-op when ``t_s <= sc.t_s``.
    """
    ens = sc.ensemble
    n = round((float(t_s) - sc.t_s) / float(dt_s))
    if n <= 0:
        return ens.cov
    if gap is None or len(gap.ambient_c) == 0:
        e = propagator(rom, sc.h, dt_s, n)
        return np.asarray(e @ ens.cov @ e.T)
    loads = None if sc.load_scale is None else np.asarray(sc.load_scale, dtype=np.float64)

    def run(h: Array, ls: Array | None, a0: Array) -> Array:
        traj = rom.simulate_state(np.maximum(h, 1e-3), gap, rom.lift(a0), load_scale=ls)
        return np.asarray(traj[-1])

    base = run(sc.h, loads, ens.a_end)
    dev = np.array(
        [
            run(
                sc.h + d_theta[:N_H],
                None if loads is None else loads + d_theta[N_H : N_H + 2],
                ens.a_end + d_a,
            )
            - base
            for d_a, d_theta in zip(ens.dev_a, ens.dev_theta, strict=True)
        ]
    )
    return np.asarray(dev.T @ dev / max(len(dev), 1))


def start_responses(rom: Any, h: Array, dt_s: float, n_steps: int, u: Array) -> Array:
    """Sensor responses (k, n_steps + 1, 32) [°C] to the start directions ``u`` (r, k) under H."""
    phi, mu = _modes(rom, h, dt_s)
    gain = np.asarray(rom.sensors) @ phi  # (32, r)
    powers = mu[None, :] ** np.arange(n_steps + 1)[:, None]  # (n+1, r)
    coeff = phi.T @ u  # (r, k)
    return np.asarray(np.einsum("sr,nr,rk->kns", gain, powers, coeff))


def end_state(problem: Any, theta: Array, *, start: Array | None = None) -> Array:
    """The reduced state (r,) at the window end for parameters θ (p,), from ``problem.t0`` or the reduced
    ``start`` (r,)."""
    loads = problem.layout.load_scale(theta)
    t0 = problem.start(theta, None if start is None else problem.model.lift(start))
    traj = problem.model.simulate_state(
        theta[:N_H], problem.inputs, t0, load_scale=None if loads is None else np.asarray(loads)
    )
    return np.asarray(traj[-1])


def carry(
    problem: Any,
    theta: Array,
    jac: Array,
    fit_cov: Array,
    start_cov: Array,
    *,
    samples: int = ENSEMBLE,
    seed: int = 0,
    normal: Array | None = None,
) -> Carried:
    """θ's total covariance and the window-end state covariance, given P₀ = ``start_cov`` (r, r) [°C²].

    ``jac`` (m, p) is the residuals' Jacobian at θ̂ over the usable entries, ``fit_cov`` (p, p) = σ²(JᵀJ)⁺
    (``normal``: a MAP fit's JᵀJ + σ²P instead of JᵀJ).
    The end covariance is the second moment about the fitted end state of an ensemble of ``samples``
    windows (``end_ensemble``; fixed ``seed``: the same window gives the same answer).
    """
    rom = problem.model
    r = int(rom.k0.shape[0])
    u = factor(check_cov(start_cov, r))
    dt, n = float(problem.inputs.dt_s), len(problem.inputs.ambient_c)
    h = np.asarray(theta[:N_H], dtype=np.float64)
    resp = problem.select(start_responses(rom, h, dt, n, u))  # (k, m)
    normal = jac.T @ jac if normal is None else normal  # a MAP fit's: JᵀJ + σ²P
    gain = -np.linalg.pinv(normal) @ (jac.T @ resp.T)  # (p, k)
    total = fit_cov + gain @ gain.T
    ens = end_ensemble(problem, theta, gain, u, fit_cov, samples=samples, seed=seed)
    return Carried(0.5 * (total + total.T), gain, ens)


def end_ensemble(
    problem: Any, theta: Array, gain: Array, u: Array, fit_cov: Array, *, samples: int, seed: int
) -> Ensemble:
    """The window-end state's error as an ensemble about the fitted end state: start coefficients
    z ~ N(0, I) and the window's noise ξ ~ N(0, ``fit_cov``) give θ = θ̂ + G·z + ξ (clipped to the box) and
    the start a₀ + U·z; each member is a full reduced run, so the map θ → a_end is not linearised (poorly
    identified H move by tens of per cent, where S·δθ misses a large part of the change)."""
    rng = np.random.default_rng(seed)
    base = end_state(problem, theta)
    lo, hi = problem.bounds[:, 0], problem.bounds[:, 1]
    noise = factor(0.5 * (fit_cov + fit_cov.T))
    a0 = problem.model.initial_state(problem.t0)
    thetas = np.empty((samples, theta.size))
    starts = np.empty((samples, a0.size))
    for i in range(samples):
        z = rng.standard_normal(u.shape[1])
        thetas[i] = np.clip(theta + gain @ z + noise @ rng.standard_normal(noise.shape[1]), lo, hi)
        starts[i] = a0 + u @ z
    dev = end_states(problem, thetas, starts) - base
    return Ensemble(base, dev, thetas - theta)


def end_states(problem: Any, thetas: Array, starts: Array) -> Array:
    """``end_state`` of each member: θ (P, p) from the reduced starts (P, r), (P, r); one batched run when
    the model has ``end_states`` (``model.rom.ReducedModel``), else one run per member."""
    batched = getattr(problem.model, "end_states", None)
    if batched is None:
        return np.array([end_state(problem, th, start=a) for th, a in zip(thetas, starts, strict=True)])
    rom = problem.model
    fields = rom.lift(starts)  # (P, N): each member's start field, as ``end_state`` gives it
    shift = problem.layout.shift(thetas)
    if shift is not None:
        fields = fields + np.asarray(shift, dtype=np.float64)[:, None]
    loads = problem.layout.load_scale(thetas)
    return np.asarray(
        batched(
            thetas[:, :N_H],
            problem.inputs,
            rom.project(fields),
            load_scale=None if loads is None else np.asarray(loads),
        )
    )
