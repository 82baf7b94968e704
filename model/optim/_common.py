"""Shared machinery of the population optimizers: result object, bounds, objective wrapper, initial population
and termination.

Error tree::

    OptimizerError(ModelError)                       (model.errors: the model layer's root)
    ├── BoundsError(OptimizerError, ValueError)      bad bounds, x0 or init (the argument is named)
    └── ObjectiveError(OptimizerError, ValueError)   the objective returned the wrong shape
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from model.errors import ModelError

FloatArray = NDArray[np.float64]
Objective = Callable[[FloatArray], Any]
Callback = Callable[["OptimizeResult"], object]
Clock = Callable[[], float]


class OptimizerError(ModelError):
    """Base of the optimizer errors."""


class BoundsError(OptimizerError, ValueError):
    """Bounds, x0 or init are malformed; the message names the argument."""


class ObjectiveError(OptimizerError, ValueError):
    """The objective returned something that is not one finite-or-inf value per candidate."""


@dataclass
class OptimizeResult:
    """Outcome of a population optimizer, shaped like ``scipy.optimize.OptimizeResult``.

    ``history[k]`` is the best objective value after iteration k (``history[0]``: the initial population),
    so ``len(history) == nit + 1``. ``population`` / ``population_fun`` are the final population, usable as
    ``init`` of a warm-started run.
    """

    x: FloatArray
    fun: float
    nfev: int
    nit: int
    success: bool
    message: str
    history: FloatArray
    population: FloatArray = field(repr=False)
    population_fun: FloatArray = field(repr=False)


def as_rng(rng: np.random.Generator | int) -> np.random.Generator:
    """A ``Generator`` from a generator or an integer seed (seeds are always injected, never global)."""
    if isinstance(rng, np.random.Generator):
        return rng
    return np.random.default_rng(rng)


def as_bounds(bounds: ArrayLike | Any) -> FloatArray:
    """Bounds as a (D, 2) array of [low, high] rows; accepts pairs or a ``scipy.optimize.Bounds``."""
    if hasattr(bounds, "lb") and hasattr(bounds, "ub"):
        bounds = np.column_stack([np.atleast_1d(bounds.lb), np.atleast_1d(bounds.ub)])
    b = np.asarray(bounds, dtype=float)
    if b.ndim != 2 or b.shape[1] != 2 or b.shape[0] < 1:
        raise BoundsError(f"bounds: expected shape (D, 2), got {b.shape}")
    if not np.all(np.isfinite(b)):
        raise BoundsError("bounds: must be finite")
    if np.any(b[:, 1] <= b[:, 0]):
        bad = int(np.argmax(b[:, 1] <= b[:, 0]))
        raise BoundsError(f"bounds[{bad}]: high must exceed low, got {b[bad].tolist()}")
    return b


def uniform(bounds: FloatArray, n: int, rng: np.random.Generator) -> FloatArray:
    """n points uniform in the box."""
    lo, hi = bounds[:, 0], bounds[:, 1]
    return lo + rng.random((n, len(bounds))) * (hi - lo)


def clip(x: FloatArray, bounds: FloatArray) -> FloatArray:
    """Project onto the box."""
    return np.clip(x, bounds[:, 0], bounds[:, 1])


def initial_population(
    bounds: FloatArray,
    popsize: int,
    rng: np.random.Generator,
    *,
    x0: ArrayLike | None = None,
    init: ArrayLike | None = None,
    x0_fraction: float = 0.5,
    x0_spread: float = 0.05,
) -> FloatArray:
    """Initial population.

    ``init`` (P, D) is used as is (its P wins over ``popsize``). Otherwise the population is uniform in the
    box, except that with ``x0`` the first ``ceil(x0_fraction * popsize)`` members are ``x0`` itself and
    Gaussian neighbours of it (sigma = ``x0_spread`` times the box width); the rest stay random so the search
    can still leave a stale warm start. With both, ``x0`` replaces the first row of ``init``.
    """
    dim = len(bounds)
    if init is not None:
        pop = np.array(init, dtype=float)
        if pop.ndim != 2 or pop.shape[1] != dim or pop.shape[0] < 1:
            raise BoundsError(f"init: expected shape (P, {dim}), got {pop.shape}")
        if not np.all(np.isfinite(pop)):
            raise BoundsError("init: must be finite")
        pop = clip(pop, bounds)
    else:
        if popsize < 1:
            raise BoundsError(f"popsize: must be >= 1, got {popsize}")
        pop = uniform(bounds, popsize, rng)
    if x0 is None:
        return pop
    x = _check_x0(x0, bounds)
    if init is not None:
        pop[0] = x
        return pop
    n_seed = max(1, int(np.ceil(x0_fraction * len(pop))))
    width = bounds[:, 1] - bounds[:, 0]
    pop[0] = x
    if n_seed > 1:
        pop[1:n_seed] = clip(x + rng.normal(size=(n_seed - 1, dim)) * x0_spread * width, bounds)
    return pop


def _check_x0(x0: ArrayLike, bounds: FloatArray) -> FloatArray:
    x = np.asarray(x0, dtype=float).reshape(-1)
    if x.shape != (len(bounds),):
        raise BoundsError(f"x0: expected {len(bounds)} values, got {x.size}")
    if not np.all(np.isfinite(x)):
        raise BoundsError("x0: must be finite")
    return clip(x, bounds)


class Evaluator:
    """Counts evaluations, enforces ``maxfev`` and turns NaN into +inf.

    With ``vectorized`` the objective takes (P, D) and returns (P,); otherwise it is called row by row and
    must return a scalar. When a batch would exceed ``maxfev`` only the allowed rows are evaluated, the rest
    get +inf and ``exhausted`` becomes true.
    """

    def __init__(self, func: Objective, *, vectorized: bool, maxfev: int | None) -> None:
        self.func = func
        self.vectorized = vectorized
        self.maxfev = maxfev
        self.nfev = 0
        self.exhausted = False

    def __call__(self, pop: FloatArray) -> FloatArray:
        n = len(pop)
        allowed = n if self.maxfev is None else max(0, min(n, self.maxfev - self.nfev))
        if allowed < n or (self.maxfev is not None and self.nfev + n >= self.maxfev):
            self.exhausted = True
        out = np.full(n, np.inf)
        if allowed > 0:
            out[:allowed] = self._raw(pop[:allowed])
            self.nfev += allowed
        return out

    def _raw(self, pop: FloatArray) -> FloatArray:
        if self.vectorized:
            vals = np.asarray(self.func(pop), dtype=float)
        else:
            vals = np.array([float(self.func(row)) for row in pop])
        if vals.shape != (len(pop),):
            raise ObjectiveError(f"objective: expected shape ({len(pop)},), got {vals.shape}")
        return np.where(np.isnan(vals), np.inf, vals)


@dataclass
class Termination:
    """Stopping rules, checked after the initial population and after every iteration.

    Success means the target was reached, or (without a target) the iteration budget ran out normally.
    """

    maxiter: int
    fun_target: float | None = None
    time_budget_s: float | None = None
    callback: Callback | None = None
    clock: Clock = time.perf_counter
    start: float = 0.0

    def begin(self) -> None:
        self.start = self.clock()

    def check(self, result: OptimizeResult, evaluator: Evaluator) -> tuple[bool, str] | None:
        """None to continue, else (success, message)."""
        if self.fun_target is not None and result.fun < self.fun_target:
            return True, f"fun < fun_target={self.fun_target:g} reached"
        if self.callback is not None and self.callback(result) is True:
            return False, "callback requested stop"
        if self.time_budget_s is not None and self.clock() - self.start >= self.time_budget_s:
            return False, f"time budget of {self.time_budget_s:g} s exhausted"
        if evaluator.exhausted:
            return False, f"evaluation budget maxfev={evaluator.maxfev} exhausted"
        if result.nit >= self.maxiter:
            if self.fun_target is None:
                return True, f"maximum number of iterations ({self.maxiter}) reached"
            return False, f"maxiter={self.maxiter} reached without fun < {self.fun_target:g}"
        return None


class Archive:
    """The best ``size`` distinct-by-rank points seen so far (the GWO leaders α, β, δ; WOA's best whale)."""

    def __init__(self, dim: int, size: int) -> None:
        self.x = np.zeros((size, dim))
        self.f = np.full(size, np.inf)

    def update(self, pop: FloatArray, fun: FloatArray) -> None:
        xs = np.vstack([self.x, pop])
        fs = np.concatenate([self.f, fun])
        order = np.argsort(fs, kind="stable")[: len(self.f)]
        self.x, self.f = xs[order].copy(), fs[order].copy()


class PopulationSolver:
    """Template of the solvers: subclasses implement ``step(t)`` and keep ``pop``, ``fun``, ``archive``."""

    def __init__(
        self,
        func: Objective,
        bounds: ArrayLike | Any,
        *,
        rng: np.random.Generator | int,
        popsize: int,
        maxiter: int,
        x0: ArrayLike | None,
        init: ArrayLike | None,
        fun_target: float | None,
        time_budget_s: float | None,
        maxfev: int | None,
        callback: Callback | None,
        vectorized: bool,
        clock: Clock,
        archive_size: int = 1,
    ) -> None:
        if maxiter < 0:
            raise BoundsError(f"maxiter: must be >= 0, got {maxiter}")
        self.bounds = as_bounds(bounds)
        self.dim = len(self.bounds)
        self.rng = as_rng(rng)
        self.maxiter = maxiter
        self.evaluate = Evaluator(func, vectorized=vectorized, maxfev=maxfev)
        self.termination = Termination(maxiter, fun_target, time_budget_s, callback, clock)
        self.pop = initial_population(self.bounds, popsize, self.rng, x0=x0, init=init)
        self.popsize = len(self.pop)
        self.fun = np.full(self.popsize, np.inf)
        self.archive = Archive(self.dim, archive_size)

    def step(self, t: int) -> None:  # pragma: no cover - abstract
        raise NotImplementedError

    def solve(self) -> OptimizeResult:
        """Run until a stopping rule fires; returns the best point ever evaluated."""
        self.termination.begin()
        self.fun = self.evaluate(self.pop)
        self.archive.update(self.pop, self.fun)
        history = [float(self.archive.f[0])]
        nit = 0
        while True:
            result = self._result(nit, history, False, "")
            verdict = self.termination.check(result, self.evaluate)
            if verdict is not None:
                result.success, result.message = verdict
                return result
            nit += 1
            self.step(nit)
            history.append(float(self.archive.f[0]))

    def _result(self, nit: int, history: Sequence[float], success: bool, message: str) -> OptimizeResult:
        return OptimizeResult(
            x=self.archive.x[0].copy(),
            fun=float(self.archive.f[0]),
            nfev=self.evaluate.nfev,
            nit=nit,
            success=success,
            message=message,
            history=np.asarray(history, dtype=float),
            population=self.pop.copy(),
            population_fun=self.fun.copy(),
        )


def linear(start: float, end: float, t: int, n: int) -> float:
    """Linear schedule: ``start`` at t = 1, ``end`` at t = n (n <= 1: ``start``)."""
    if n <= 1:
        return start
    return start + (end - start) * (t - 1) / (n - 1)
