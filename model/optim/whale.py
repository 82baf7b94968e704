"""Whale optimization algorithm (Mirjalili & Lewis 2016), a baseline of the paper.

Per whale and iteration: a falls linearly 2 → 0, A = 2a·r1 − a, C = 2·r2 (scalars per whale, as in the
original code), l uniform in [a2, 1] with a2 falling −1 → −2, p uniform. If p < 0.5: encircle the best
whale X* (|A| < 1, D = |C·X* − X|, X' = X* − A·D) or search around a random whale Xr (|A| >= 1). Otherwise
the bubble-net spiral X' = |X* − X|·e^(b·l)·cos(2πl) + X*, b = 1.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from model.optim._common import (
    Callback,
    Clock,
    FloatArray,
    Objective,
    OptimizeResult,
    PopulationSolver,
    clip,
    linear,
)


class WhaleSolver(PopulationSolver):
    """WOA state; use :func:`whale`."""

    def __init__(self, func: Objective, bounds: ArrayLike | Any, *, spiral_b: float, **common: Any) -> None:
        super().__init__(func, bounds, archive_size=1, **common)
        self.spiral_b = spiral_b

    def step(self, t: int) -> None:
        a = linear(2.0, 0.0, t, self.maxiter)
        a2 = linear(-1.0, -2.0, t, self.maxiter)
        new = clip(self._move(a, a2), self.bounds)
        self.pop, self.fun = new, self.evaluate(new)
        self.archive.update(self.pop, self.fun)

    def _move(self, a: float, a2: float) -> FloatArray:
        n = self.popsize
        best = self.archive.x[0][None, :]
        big_a = (2.0 * a * self.rng.random(n) - a)[:, None]
        big_c = (2.0 * self.rng.random(n))[:, None]
        ell = ((a2 - 1.0) * self.rng.random(n) + 1.0)[:, None]
        p = self.rng.random(n)[:, None]
        partner = self.pop[self.rng.integers(0, n, size=n)]
        target = np.where(np.abs(big_a) < 1.0, best, partner)
        encircle = target - big_a * np.abs(big_c * target - self.pop)
        spiral = np.abs(best - self.pop) * np.exp(self.spiral_b * ell) * np.cos(2.0 * np.pi * ell) + best
        result: FloatArray = np.where(p < 0.5, encircle, spiral)
        return result


def whale(
    func: Objective,
    bounds: ArrayLike | Any,
    *,
    rng: np.random.Generator | int,
    x0: ArrayLike | None = None,
    init: ArrayLike | None = None,
    popsize: int = 7,
    maxiter: int = 100,
    spiral_b: float = 1.0,
    fun_target: float | None = None,
    time_budget_s: float | None = None,
    maxfev: int | None = None,
    callback: Callback | None = None,
    vectorized: bool = True,
    clock: Clock = time.perf_counter,
) -> OptimizeResult:
    """Minimize ``func`` over ``bounds`` with WOA; arguments and result as in ``grey_wolf``."""
    solver = WhaleSolver(
        func,
        bounds,
        spiral_b=spiral_b,
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
