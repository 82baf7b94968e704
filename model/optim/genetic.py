"""Real-coded genetic algorithm, a baseline of the paper.

Each generation keeps the ``elite`` best members and fills the rest with children: tournament selection (size
``tournament``, default 3), crossover with probability ``crossover_prob`` (BLX-α blend, default, or SBX with
index ``eta_c``; blend was clearly better on the sphere at a few hundred evaluations), then mutation of
each gene with probability ``mutation_prob`` (default 1/D; polynomial with index ``eta_m``, or Gaussian
with sigma ``sigma`` times the box width), clipped to the box.
"""

from __future__ import annotations

import time
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike

from model.optim._common import (
    BoundsError,
    Callback,
    Clock,
    FloatArray,
    Objective,
    OptimizeResult,
    PopulationSolver,
    clip,
)

Crossover = Literal["sbx", "blend"]
Mutation = Literal["polynomial", "gaussian"]


def sbx(
    p1: FloatArray, p2: FloatArray, eta: float, rng: np.random.Generator
) -> tuple[FloatArray, FloatArray]:
    """Simulated binary crossover (Deb & Agrawal 1995), unbounded form; the caller clips."""
    u = rng.random(p1.shape)
    beta = np.where(u <= 0.5, (2.0 * u) ** (1.0 / (eta + 1.0)), (0.5 / (1.0 - u)) ** (1.0 / (eta + 1.0)))
    mean, half = 0.5 * (p1 + p2), 0.5 * beta * (p2 - p1)
    return mean - half, mean + half


def blend(
    p1: FloatArray, p2: FloatArray, alpha: float, rng: np.random.Generator
) -> tuple[FloatArray, FloatArray]:
    """BLX-α: children uniform in the parents' interval widened by α on both sides."""
    lo, hi = np.minimum(p1, p2), np.maximum(p1, p2)
    span = hi - lo
    lo, hi = lo - alpha * span, hi + alpha * span
    return lo + rng.random(p1.shape) * (hi - lo), lo + rng.random(p1.shape) * (hi - lo)


def polynomial_mutation(
    x: FloatArray, bounds: FloatArray, eta: float, rng: np.random.Generator
) -> FloatArray:
    """Deb's polynomial mutation of every entry of x (the caller selects which entries)."""
    u = rng.random(x.shape)
    delta = np.where(
        u < 0.5, (2.0 * u) ** (1.0 / (eta + 1.0)) - 1.0, 1.0 - (2.0 * (1.0 - u)) ** (1.0 / (eta + 1.0))
    )
    width = np.broadcast_to(bounds[:, 1] - bounds[:, 0], x.shape)
    result: FloatArray = x + delta * width
    return result


class GeneticSolver(PopulationSolver):
    """GA state; use :func:`genetic`."""

    def __init__(
        self, func: Objective, bounds: ArrayLike | Any, *, options: dict[str, Any], **common: Any
    ) -> None:
        super().__init__(func, bounds, archive_size=1, **common)
        if options["crossover"] not in ("sbx", "blend"):
            raise BoundsError(f"crossover: expected 'sbx' or 'blend', got {options['crossover']!r}")
        if options["mutation"] not in ("polynomial", "gaussian"):
            raise BoundsError(f"mutation: expected 'polynomial' or 'gaussian', got {options['mutation']!r}")
        self.opt = options
        self.elite = min(int(options["elite"]), self.popsize - 1) if self.popsize > 1 else 0
        mp = options["mutation_prob"]
        self.mutation_prob = 1.0 / self.dim if mp is None else float(mp)

    def step(self, t: int) -> None:
        n_child = self.popsize - self.elite
        order = np.argsort(self.fun, kind="stable")
        keep_x, keep_f = self.pop[order[: self.elite]], self.fun[order[: self.elite]]
        children = clip(self._mutate(self._crossover(n_child)), self.bounds)
        child_f = self.evaluate(children)
        self.pop = np.vstack([keep_x, children])
        self.fun = np.concatenate([keep_f, child_f])
        self.archive.update(children, child_f)

    def _select(self, n: int) -> FloatArray:
        contenders = self.rng.integers(0, self.popsize, size=(n, max(1, int(self.opt["tournament"]))))
        winners = contenders[np.arange(n), np.argmin(self.fun[contenders], axis=1)]
        return self.pop[winners]

    def _crossover(self, n_child: int) -> FloatArray:
        n_pairs = (n_child + 1) // 2
        p1, p2 = self._select(n_pairs), self._select(n_pairs)
        if self.opt["crossover"] == "sbx":
            c1, c2 = sbx(p1, p2, self.opt["eta_c"], self.rng)
        else:
            c1, c2 = blend(p1, p2, self.opt["blend_alpha"], self.rng)
        cross = (self.rng.random(n_pairs) < self.opt["crossover_prob"])[:, None]
        c1, c2 = np.where(cross, c1, p1), np.where(cross, c2, p2)
        return np.vstack([c1, c2])[:n_child]

    def _mutate(self, x: FloatArray) -> FloatArray:
        hit = self.rng.random(x.shape) < self.mutation_prob
        if self.opt["mutation"] == "polynomial":
            mutated = polynomial_mutation(x, self.bounds, self.opt["eta_m"], self.rng)
        else:
            width = self.bounds[:, 1] - self.bounds[:, 0]
            mutated = x + self.rng.normal(size=x.shape) * self.opt["sigma"] * width
        result: FloatArray = np.where(hit, mutated, x)
        return result


def genetic(
    func: Objective,
    bounds: ArrayLike | Any,
    *,
    rng: np.random.Generator | int,
    x0: ArrayLike | None = None,
    init: ArrayLike | None = None,
    popsize: int = 7,
    maxiter: int = 100,
    crossover: Crossover = "blend",
    mutation: Mutation = "polynomial",
    tournament: int = 3,
    elite: int = 1,
    crossover_prob: float = 0.9,
    mutation_prob: float | None = None,
    eta_c: float = 15.0,
    eta_m: float = 20.0,
    blend_alpha: float = 0.5,
    sigma: float = 0.1,
    fun_target: float | None = None,
    time_budget_s: float | None = None,
    maxfev: int | None = None,
    callback: Callback | None = None,
    vectorized: bool = True,
    clock: Clock = time.perf_counter,
) -> OptimizeResult:
    """Minimize ``func`` over ``bounds`` with a real-coded GA (one generation per iteration).

    Arguments and result as in :func:`model.optim.grey_wolf`; the GA-specific ones are described in the module
    docstring. A generation costs ``popsize - elite`` evaluations.
    """
    options = {
        "crossover": crossover,
        "mutation": mutation,
        "tournament": tournament,
        "elite": elite,
        "crossover_prob": crossover_prob,
        "mutation_prob": mutation_prob,
        "eta_c": eta_c,
        "eta_m": eta_m,
        "blend_alpha": blend_alpha,
        "sigma": sigma,
    }
    solver = GeneticSolver(
        func,
        bounds,
        options=options,
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
