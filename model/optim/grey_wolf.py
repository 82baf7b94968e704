"""Grey wolf optimizer: standard GWO (Mirjalili et al. 2014) and the paper's IGWO (Pian & Li 2025), SPEC §2.

GWO: every wolf moves towards each leader p in {α, β, δ} with D = |C·Xp − X|, Xp' = Xp − A·D, A = 2a·r1 − a,
C = 2·r2 (fresh r1, r2 per leader and dimension) and X(t+1) = (X1 + X2 + X3)/3; a falls linearly from
``a_start`` to ``a_end``. The leaders are the three best points evaluated so far.

IGWO adds (1) the weights ω1 = 1/3, ω2 = 3x/(1+6x), ω3 = (18x²+3x)/(1+18x+18x²) with x = |A⊙C| per dimension
and one (A, C) shared by the three leaders; ``weights="paper"`` divides Σωi·Xi by 3 as printed (which
pulls every wolf towards the origin since Σω < 3), ``"normalized"`` divides by Σω; (2) the probabilistic
perturbation P(t) = (G−1)/(4G)·e^((t−1)/k): with probability P a wolf proposes M uniform in the box, kept
only if f(M) < f(X(t+1)); (3) re-seeding, uniform in the box, of a wolf whose own best has not improved for
``k_stall`` iterations. Perturbation and re-seeding are the IGWO defaults and off for plain GWO.
"""

from __future__ import annotations

import time
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from model.optim._common import (
    BoundsError,
    Callback,
    Clock,
    FloatArray,
    Objective,
    OptimizeResult,
    PopulationSolver,
    clip,
    linear,
    uniform,
)

Variant = Literal["igwo", "gwo"]
Weights = Literal["normalized", "paper"]


def igwo_weights(x: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """The paper's leader weights (ω1, ω2, ω3) for x = |A⊙C| >= 0, elementwise (SPEC §2)."""
    w1 = np.full_like(x, 1.0 / 3.0)
    w2 = 3.0 * x / (1.0 + 6.0 * x)
    w3 = (18.0 * x * x + 3.0 * x) / (1.0 + 18.0 * x + 18.0 * x * x)
    return w1, w2, w3


def perturbation_probability(t: int, *, dim: int, maxiter: int) -> float:
    """P(t) = (G−1)/(4G)·e^((t−1)/k), G the problem dimension, k the maximum iteration count, t from 1."""
    k = max(maxiter, 1)
    return (dim - 1) / (4.0 * dim) * float(np.exp((t - 1) / k))


def expected_evals_per_iteration(popsize: int, *, dim: int, maxiter: int, perturbation: bool = True) -> float:
    """Mean evaluations per IGWO iteration (the wolves plus the expected perturbation proposals)."""
    if not perturbation:
        return float(popsize)
    mean_p = np.mean(
        [min(1.0, perturbation_probability(t, dim=dim, maxiter=maxiter)) for t in range(1, maxiter + 1)]
    )
    return popsize * (1.0 + float(mean_p))


class GreyWolfSolver(PopulationSolver):
    """GWO / IGWO state; use :func:`grey_wolf`."""

    def __init__(
        self,
        func: Objective,
        bounds: ArrayLike | Any,
        *,
        variant: Variant,
        weights: Weights,
        a_start: float,
        a_end: float,
        perturbation: bool,
        k_stall: int,
        **common: Any,
    ) -> None:
        super().__init__(func, bounds, archive_size=3, **common)
        if variant not in ("igwo", "gwo"):
            raise BoundsError(f"variant: expected 'igwo' or 'gwo', got {variant!r}")
        if weights not in ("normalized", "paper"):
            raise BoundsError(f"weights: expected 'normalized' or 'paper', got {weights!r}")
        self.variant = variant
        self.weights = weights
        self.a_start, self.a_end = a_start, a_end
        self.perturbation = perturbation
        self.k_stall = k_stall
        self.own_best = np.full(self.popsize, np.inf)
        self.stall = np.zeros(self.popsize, dtype=int)

    def step(self, t: int) -> None:
        if t == 1:
            self.own_best = self.fun.copy()
        a = linear(self.a_start, self.a_end, t, self.maxiter)
        new = clip(self._move(a), self.bounds)
        chosen, proposals = self._proposals(t)
        # one objective call for the moved wolves and the perturbation proposals (same algorithm, fewer calls)
        both = self.evaluate(np.vstack([new, proposals]))
        fun, f_prop = both[: self.popsize], both[self.popsize :]
        better = f_prop < fun[chosen]
        new[chosen[better]] = proposals[better]
        fun[chosen[better]] = f_prop[better]
        self._track_stall(new, fun)
        self.pop, self.fun = new, fun
        self.archive.update(new, fun)

    def _move(self, a: float) -> FloatArray:
        leaders = self.archive.x[:, None, :]  # (3, 1, D)
        x = self.pop[None, :, :]  # (1, P, D)
        shape = (self.popsize, self.dim)
        if self.variant == "gwo":
            big_a = 2.0 * a * self.rng.random((3, *shape)) - a
            big_c = 2.0 * self.rng.random((3, *shape))
            moved = leaders - big_a * np.abs(big_c * leaders - x)
            return moved.mean(axis=0)
        big_a = 2.0 * a * self.rng.random(shape) - a
        big_c = 2.0 * self.rng.random(shape)
        moved = leaders - big_a * np.abs(big_c * leaders - x)
        w1, w2, w3 = igwo_weights(np.abs(big_a * big_c))
        total = w1 * moved[0] + w2 * moved[1] + w3 * moved[2]
        return total / 3.0 if self.weights == "paper" else total / (w1 + w2 + w3)

    def _proposals(self, t: int) -> tuple[NDArray[np.intp], FloatArray]:
        """Wolves chosen for the perturbation (probability P(t)) and their uniform proposals M."""
        if not self.perturbation:
            return np.zeros(0, dtype=np.intp), np.zeros((0, self.dim))
        p = perturbation_probability(t, dim=self.dim, maxiter=self.maxiter)
        chosen = np.flatnonzero(self.rng.random(self.popsize) < p)
        return chosen, uniform(self.bounds, chosen.size, self.rng)

    def _track_stall(self, new: FloatArray, fun: FloatArray) -> None:
        improved = fun < self.own_best
        self.own_best = np.minimum(self.own_best, fun)
        self.stall = np.where(improved, 0, self.stall + 1)
        if self.k_stall <= 0:
            return
        stalled = np.flatnonzero(self.stall >= self.k_stall)
        if stalled.size == 0:
            return
        new[stalled] = uniform(self.bounds, stalled.size, self.rng)
        fun[stalled] = self.evaluate(new[stalled])
        self.own_best[stalled] = fun[stalled]
        self.stall[stalled] = 0


def grey_wolf(
    func: Objective,
    bounds: ArrayLike | Any,
    *,
    rng: np.random.Generator | int,
    variant: Variant = "igwo",
    weights: Weights = "normalized",
    x0: ArrayLike | None = None,
    init: ArrayLike | None = None,
    popsize: int = 7,
    maxiter: int = 100,
    a_start: float = 2.0,
    a_end: float = 0.001,
    perturbation: bool | None = None,
    k_stall: int | None = None,
    fun_target: float | None = None,
    time_budget_s: float | None = None,
    maxfev: int | None = None,
    callback: Callback | None = None,
    vectorized: bool = True,
    clock: Clock = time.perf_counter,
) -> OptimizeResult:
    """Minimize ``func`` over the box ``bounds`` with IGWO (default) or standard GWO.

    Args:
        func: objective; with ``vectorized`` it takes the population (P, D) and returns (P,), else one (D,)
            point.
        bounds: (D, 2) [low, high] per dimension, or a ``scipy.optimize.Bounds``; every candidate is clipped
            to it.
        rng: generator or seed; the same seed gives the identical result.
        variant: ``"igwo"`` (weights, perturbation, re-seeding) or ``"gwo"`` (Mirjalili 2014).
        weights: IGWO only: ``"normalized"`` (Σω·X/Σω, default) or ``"paper"`` (Σω·X/3, literal).
        x0: warm start: the population is seeded around it (half), the rest random.
        init: full initial population (P, D), e.g. ``result.population`` of an earlier run.
        popsize, maxiter: paper's Table 3 defaults 7 and 100.
        a_start, a_end: the linear control parameter schedule (paper: 2.0 → 0.001).
        perturbation: probabilistic perturbation; None means on for IGWO, off for GWO.
        k_stall: re-seed a wolf after this many iterations without own improvement; None means
            max(5, maxiter // 5) for IGWO and off for GWO; 0 switches it off.
        fun_target: stop as soon as the best value is < fun_target (paper: fit > 0.5 ⇔ f < 1).
        time_budget_s: stop after this wall time [s], measured with ``clock``.
        maxfev: hard cap on objective evaluations.
        callback: called with the intermediate result after each iteration; returning True stops.

    Returns:
        OptimizeResult with x, fun, nfev, nit, success, message, history (best per iteration) and the final
        population.
    """
    igwo = variant == "igwo"
    if k_stall is None:
        k_stall = max(5, maxiter // 5) if igwo else 0
    solver = GreyWolfSolver(
        func,
        bounds,
        variant=variant,
        weights=weights,
        a_start=a_start,
        a_end=a_end,
        perturbation=igwo if perturbation is None else perturbation,
        k_stall=k_stall,
        rng=rng,
        popsize=popsize,
        maxiter=maxiter,
        x0=x0,
        init=init,
        fun_target=fun_target,
        time_budget_s=time_budget_s,
        maxfev=maxfev,
        callback=callback,
        vectorized=vectorized,
        clock=clock,
    )
    return solver.solve()
