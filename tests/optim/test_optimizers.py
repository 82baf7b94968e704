"""Behaviour of the population optimizers on the benchmark functions."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import pytest

from benchmarks.studies import benchfuncs as bf
from model.optim import BoundsError, ObjectiveError, OptimizeResult, genetic, grey_wolf, whale
from model.optim.grey_wolf import igwo_weights, perturbation_probability

Solver = Callable[..., OptimizeResult]
SOLVERS: dict[str, tuple[Solver, dict[str, Any]]] = {
    "igwo-normalized": (grey_wolf, {}),
    "igwo-paper": (grey_wolf, {"weights": "paper"}),
    "gwo": (grey_wolf, {"variant": "gwo"}),
    "woa": (whale, {}),
    "ga": (genetic, {}),
}


def _start_median(f: bf.BenchmarkFunction, seed: int = 0) -> float:
    lo, hi = f.bounds[:, 0], f.bounds[:, 1]
    pts = lo + np.random.default_rng(seed).random((200, f.dim)) * (hi - lo)
    return float(np.median(f(pts)))


@pytest.mark.parametrize("label", list(SOLVERS))
def test_reduces_sphere_well_below_start_in_a_few_hundred_evaluations(label: str) -> None:
    solver, kw = SOLVERS[label]
    f = bf.make("F1")
    res = solver(f, f.bounds, rng=1, popsize=10, maxiter=40, maxfev=400, **kw)
    assert res.nfev <= 400
    assert res.fun < 0.3 * _start_median(f)
    assert res.fun == pytest.approx(f(res.x)[0])
    assert np.all(np.diff(res.history) <= 0.0)
    assert len(res.history) == res.nit + 1


@pytest.mark.parametrize("label", ["igwo-normalized", "gwo", "ga"])
@pytest.mark.parametrize("name", ["F1", "F9"])
def test_shifted_functions_are_improved(label: str, name: str) -> None:
    solver, kw = SOLVERS[label]
    f = bf.make(name, shifted=True)
    res = solver(f, f.bounds, rng=2, popsize=20, maxiter=100, **kw)
    assert res.fun < 0.3 * _start_median(f)
    assert res.fun < f(np.zeros((1, f.dim)))[0]  # better than just going to the origin


@pytest.mark.parametrize("label", list(SOLVERS))
def test_same_seed_same_result_different_seed_different(label: str) -> None:
    solver, kw = SOLVERS[label]
    f = bf.make("F9", shifted=True)
    a = solver(f, f.bounds, rng=7, popsize=8, maxiter=20, **kw)
    b = solver(f, f.bounds, rng=np.random.default_rng(7), popsize=8, maxiter=20, **kw)
    c = solver(f, f.bounds, rng=8, popsize=8, maxiter=20, **kw)
    np.testing.assert_array_equal(a.x, b.x)
    np.testing.assert_array_equal(a.history, b.history)
    assert a.nfev == b.nfev
    assert not np.array_equal(a.x, c.x)


@pytest.mark.parametrize("label", list(SOLVERS))
def test_every_evaluated_point_is_inside_the_bounds(label: str) -> None:
    solver, kw = SOLVERS[label]
    bounds = np.array([[1.0, 2.0], [-5.0, -4.0], [0.0, 100.0]])
    seen: list[np.ndarray] = []

    def func(x: np.ndarray) -> np.ndarray:
        seen.append(x.copy())
        return np.sum((x - np.array([10.0, 10.0, 10.0])) ** 2, axis=1)  # optimum outside the box

    res = solver(func, bounds, rng=3, popsize=9, maxiter=80, **kw)
    pts = np.vstack(seen)
    assert np.all(pts >= bounds[:, 0]) and np.all(pts <= bounds[:, 1])
    if label != "igwo-paper":  # the literal update is pulled towards 0 (tested below)
        assert res.x[0] == pytest.approx(2.0, abs=0.25) and res.x[1] == pytest.approx(-4.0, abs=0.25)
    assert res.nfev == len(pts)


@pytest.mark.parametrize("label", list(SOLVERS))
def test_warm_start_at_the_optimum_succeeds_immediately(label: str) -> None:
    solver, kw = SOLVERS[label]
    f = bf.make("F1", shifted=True)
    cold = solver(f, f.bounds, rng=4, popsize=7, maxiter=100, fun_target=1.0, **kw)
    warm = solver(f, f.bounds, rng=4, popsize=7, maxiter=100, fun_target=1.0, x0=f.x_opt, **kw)
    assert warm.success and warm.nit == 0 and warm.nfev == 7
    assert warm.fun < 1.0
    assert cold.nfev > warm.nfev


def test_warm_start_near_optimum_with_low_a_start_converges_faster_than_cold() -> None:
    """A warm start only pays with a smaller a_start: at a = 2 the exploration scatters the pack anyway."""
    truth = np.array([88.21, 46.32, 68.49, 46.72, 52.13, 70.23, 16.54])

    def func(x: np.ndarray) -> np.ndarray:
        return np.sum(((x - truth) / truth) ** 2, axis=1)

    bounds = [[5.0, 200.0]] * 7
    kw: dict[str, Any] = {"popsize": 7, "maxiter": 100, "fun_target": 3e-3}
    warm = [grey_wolf(func, bounds, rng=s, x0=1.1 * truth, a_start=0.2, **kw) for s in range(7)]
    cold = [grey_wolf(func, bounds, rng=s, **kw) for s in range(7)]
    assert all(r.success for r in warm + cold)
    assert np.median([r.nfev for r in warm]) < 0.5 * np.median([r.nfev for r in cold])


def test_init_population_is_used_and_x0_rows_are_seeded() -> None:
    f = bf.make("F1")
    init = np.tile(f.x_opt, (5, 1)) + 1e-3
    res = grey_wolf(f, f.bounds, rng=0, init=init, maxiter=0)
    np.testing.assert_allclose(res.population, init)
    assert res.nit == 0 and res.nfev == 5 and res.fun < 1e-4
    with pytest.raises(BoundsError, match="init"):
        grey_wolf(f, f.bounds, rng=0, init=np.zeros((5, 3)))
    with pytest.raises(BoundsError, match="x0"):
        grey_wolf(f, f.bounds, rng=0, x0=np.zeros(3))


def test_fun_target_stops_early_with_success() -> None:
    f = bf.make("F1")
    full = grey_wolf(f, f.bounds, rng=5, popsize=10, maxiter=200)
    early = grey_wolf(f, f.bounds, rng=5, popsize=10, maxiter=200, fun_target=100.0)
    assert early.success and early.fun < 100.0 and "fun_target" in early.message
    assert early.nit < full.nit
    # the first iteration below the target is where it stopped
    assert early.nit == int(np.argmax(full.history < 100.0))
    never = grey_wolf(f, f.bounds, rng=5, popsize=10, maxiter=10, fun_target=-1.0)
    assert not never.success and "maxiter" in never.message


def test_time_budget_stops_with_injected_clock() -> None:
    f = bf.make("F1")
    ticks = iter(np.arange(0.0, 1000.0, 1.0))

    def clock() -> float:
        return float(next(ticks))

    res = grey_wolf(f, f.bounds, rng=0, maxiter=1000, time_budget_s=5.0, clock=clock)
    assert not res.success and "time budget" in res.message
    assert 1 <= res.nit <= 5


def test_maxfev_caps_evaluations_and_callback_can_stop() -> None:
    f = bf.make("F9")
    res = grey_wolf(f, f.bounds, rng=0, popsize=7, maxiter=1000, maxfev=100)
    assert res.nfev == 100 and "maxfev" in res.message
    calls: list[int] = []

    def cb(r: OptimizeResult) -> bool:
        calls.append(r.nit)
        return r.nit >= 3

    res = whale(f, f.bounds, rng=0, maxiter=50, callback=cb)
    assert res.nit == 3 and calls == [0, 1, 2, 3] and "callback" in res.message


def test_non_vectorized_objective_gives_the_same_result() -> None:
    f = bf.make("F2", shifted=True)
    a = grey_wolf(f, f.bounds, rng=9, maxiter=20)
    b = grey_wolf(lambda x: float(f(x[None, :])[0]), f.bounds, rng=9, maxiter=20, vectorized=False)
    np.testing.assert_array_equal(a.x, b.x)


def test_bad_inputs_raise_typed_errors() -> None:
    with pytest.raises(BoundsError, match=r"bounds\[1\]"):
        grey_wolf(bf.sphere, [[0, 1], [2, 1]], rng=0)
    with pytest.raises(ObjectiveError, match="shape"):
        grey_wolf(lambda x: np.zeros(3), [[0, 1], [0, 1]], rng=0, popsize=5)
    with pytest.raises(BoundsError, match="variant"):
        grey_wolf(bf.sphere, [[0, 1]], rng=0, variant="xx")  # type: ignore[arg-type]


def test_nan_objective_values_are_never_chosen() -> None:
    def func(x: np.ndarray) -> np.ndarray:
        v = np.sum(x * x, axis=1)
        return np.where(x[:, 0] < 0.0, np.nan, v)

    res = grey_wolf(func, [[-1.0, 1.0], [-1.0, 1.0]], rng=0, popsize=10, maxiter=30)
    assert np.isfinite(res.fun) and res.x[0] >= 0.0


def test_igwo_weights_match_the_printed_formulas() -> None:
    x = np.array([0.0, 0.5, 1.0, 4.0])
    w1, w2, w3 = igwo_weights(x)
    np.testing.assert_allclose(w1, 1 / 3)
    np.testing.assert_allclose(w2, [0.0, 1.5 / 4.0, 3.0 / 7.0, 12.0 / 25.0])
    np.testing.assert_allclose(w3, [0.0, 6.0 / 14.5, 21.0 / 37.0, 300.0 / 361.0])
    assert np.all(w1 + w2 + w3 < 3.0)
    assert perturbation_probability(1, dim=30, maxiter=100) == pytest.approx(29 / 120)
    assert perturbation_probability(101, dim=30, maxiter=100) == pytest.approx(29 / 120 * np.e)


def test_paper_weights_pull_towards_the_origin_on_a_shifted_function() -> None:
    """SPEC §2: the literal /3 update contracts every wolf towards 0; that only pays for an optimum at 0."""
    plain, shifted = bf.make("F1"), bf.make("F1", shifted=True)
    dist_paper, dist_norm, gap_paper, gap_norm = [], [], [], []
    for seed in range(5):
        kw: dict[str, Any] = {"rng": seed, "popsize": 20, "maxiter": 150}
        rp = grey_wolf(shifted, shifted.bounds, weights="paper", **kw)
        rn = grey_wolf(shifted, shifted.bounds, weights="normalized", **kw)
        # distance of the final population to the origin relative to the distance to the optimum
        dist_paper.append(np.median(np.linalg.norm(rp.population, axis=1)))
        dist_norm.append(np.median(np.linalg.norm(rn.population, axis=1)))
        gap_paper.append(rp.fun)
        gap_norm.append(rn.fun)
        up = grey_wolf(plain, plain.bounds, weights="paper", **kw)
        un = grey_wolf(plain, plain.bounds, weights="normalized", **kw)
        assert up.fun < un.fun  # the flattering case: optimum at the origin
    shift_norm = np.linalg.norm(shifted.x_opt)
    assert np.median(dist_paper) < 0.5 * shift_norm  # the paper's population sits near the origin
    assert np.median(dist_norm) > 0.5 * shift_norm  # the normalized one near the true optimum
    assert np.median(gap_paper) > 5.0 * np.median(gap_norm)
