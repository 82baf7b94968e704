"""Population optimizers shaped like ``scipy.optimize`` (STYLE rule 5).

``grey_wolf`` (IGWO of the paper, or standard GWO), ``whale`` (WOA) and ``genetic`` (real-coded GA) share one
interface: ``f(func, bounds, *, rng, x0=None, init=None, popsize, maxiter, fun_target, time_budget_s, maxfev,
callback, vectorized, clock) -> OptimizeResult``. The objective takes a whole population (P, D) → (P,) when
``vectorized``. The paper's Table 1 functions are the laboratory's (``benchmarks.studies.benchfuncs``).
"""

from model.optim._common import BoundsError, ObjectiveError, OptimizerError, OptimizeResult
from model.optim.genetic import genetic
from model.optim.grey_wolf import grey_wolf
from model.optim.whale import whale

__all__ = [
    "BoundsError",
    "ObjectiveError",
    "OptimizeResult",
    "OptimizerError",
    "genetic",
    "grey_wolf",
    "whale",
]
