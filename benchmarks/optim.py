"""``python -m benchmarks optim``: IGWO (paper / normalized weights), GWO, WOA, GA and mealpy's GWO on the
paper's Table 1 functions (F1, F2, F7, F9, 30 dimensions) and shifted versions, at equal evaluation budgets.

Every method gets the same population size and the same hard cap on objective evaluations (``--budget``);
the iteration count of each is chosen so that its schedule (a → a_end) ends at that budget. The figures are
medians over ``--seeds`` seeds of the final (noise-free) objective value, the evaluations used and the wall
time. The last lines say whether the paper's ranking (IGWO best, then GWO, WOA, GA; paper Fig. 5) holds.
"""

from __future__ import annotations

import argparse
import itertools
import time
from collections.abc import Callable
from datetime import UTC, datetime
from typing import Any

import numpy as np

from benchmarks.studies import benchfuncs as bf
from benchmarks.targets import format_verdicts, report
from model.optim import OptimizeResult, genetic, grey_wolf, whale
from model.optim.grey_wolf import Variant, Weights, expected_evals_per_iteration

Runner = Callable[[bf.BenchmarkFunction, int, int, int], OptimizeResult]
METHODS = ("igwo-paper", "igwo-normalized", "gwo", "woa", "ga")
PAPER_ORDER = ("igwo", "gwo", "woa", "ga")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--json", action="store_true", help="print JSON instead of tables")
    parser.add_argument("--seeds", type=int, default=10, help="seeds per method and function (default 10)")
    parser.add_argument(
        "--budget", type=int, default=6000, help="objective evaluations per run (default 6000)"
    )
    parser.add_argument("--popsize", type=int, default=30, help="population of every method (default 30)")
    parser.add_argument("--dim", type=int, default=30, help="problem dimension (paper: 30)")
    parser.add_argument("--functions", default="F1,F2,F7,F9", help="comma-separated subset of F1,F2,F7,F9")
    parser.add_argument("--no-peer", action="store_true", help="skip mealpy's GWO even when installed")


def _igwo_iterations(popsize: int, budget: int, dim: int) -> int:
    guess = max(1, (budget - popsize) // popsize)
    for _ in range(3):
        per_iter = expected_evals_per_iteration(popsize, dim=dim, maxiter=guess)
        guess = max(1, int((budget - popsize) / per_iter))
    return guess


def _runners(popsize: int, budget: int, dim: int) -> dict[str, Runner]:
    it_plain = max(1, (budget - popsize) // popsize)
    it_ga = max(1, (budget - popsize) // max(1, popsize - 1))
    it_igwo = _igwo_iterations(popsize, budget, dim)

    def gw(variant: Variant, weights: Weights, maxiter: int) -> Runner:
        def run(f: bf.BenchmarkFunction, seed: int, pop: int, cap: int) -> OptimizeResult:
            return grey_wolf(
                f,
                f.bounds,
                rng=seed,
                variant=variant,
                weights=weights,
                popsize=pop,
                maxiter=maxiter,
                maxfev=cap,
            )

        return run

    def woa(f: bf.BenchmarkFunction, seed: int, pop: int, cap: int) -> OptimizeResult:
        return whale(f, f.bounds, rng=seed, popsize=pop, maxiter=it_plain, maxfev=cap)

    def ga(f: bf.BenchmarkFunction, seed: int, pop: int, cap: int) -> OptimizeResult:
        return genetic(f, f.bounds, rng=seed, popsize=pop, maxiter=it_ga, maxfev=cap)

    return {
        "igwo-paper": gw("igwo", "paper", it_igwo),
        "igwo-normalized": gw("igwo", "normalized", it_igwo),
        "gwo": gw("gwo", "normalized", it_plain),
        "woa": woa,
        "ga": ga,
    }


def _mealpy_runner(popsize: int, budget: int) -> Runner | None:
    try:
        from mealpy import GWO, FloatVar
    except ImportError:
        return None
    epochs = max(1, (budget - popsize) // popsize)

    def run(f: bf.BenchmarkFunction, seed: int, pop: int, cap: int) -> OptimizeResult:
        count = [0]

        def obj(x: np.ndarray) -> float:
            count[0] += 1
            return float(f(x[None, :])[0])

        problem = {
            "obj_func": obj,
            "bounds": FloatVar(lb=f.bounds[:, 0], ub=f.bounds[:, 1]),
            "minmax": "min",
            "log_to": None,
        }
        model = GWO.OriginalGWO(epoch=epochs, pop_size=pop)
        best = model.solve(problem, seed=seed)
        x = np.asarray(best.solution, dtype=float)
        hist = np.asarray(model.history.list_global_best_fit, dtype=float)
        return OptimizeResult(
            x=x,
            fun=float(best.target.fitness),
            nfev=count[0],
            nit=epochs,
            success=True,
            message="mealpy",
            history=hist,
            population=x[None],
            population_fun=hist[-1:],
        )

    return run


def _stats(values: list[float]) -> dict[str, float]:
    q25, med, q75 = np.percentile(values, [25, 50, 75])
    return {"median": float(med), "q25": float(q25), "q75": float(q75)}


def _run_method(runner: Runner, f_name: str, shifted: bool, args: argparse.Namespace) -> dict[str, Any]:
    finals, nfevs, walls = [], [], []
    for seed in range(args.seeds):
        f = bf.make(f_name, dim=args.dim, shifted=shifted, noise_rng=1000 + seed)
        t0 = time.perf_counter()
        res = runner(f, seed, args.popsize, args.budget)
        walls.append(time.perf_counter() - t0)
        finals.append(float(f.noise_free(res.x)[0]))
        nfevs.append(float(res.nfev))
    return {
        "fun": _stats(finals),
        "nfev_median": float(np.median(nfevs)),
        "wall_s_median": float(np.median(walls)),
    }


def _ranking(methods: dict[str, dict[str, Any]]) -> list[str]:
    return sorted(methods, key=lambda m: methods[m]["fun"]["median"])


def _paper_order_holds(methods: dict[str, dict[str, Any]], igwo: str) -> bool:
    meds = [methods[igwo if m == "igwo" else m]["fun"]["median"] for m in PAPER_ORDER]
    return all(a <= b for a, b in itertools.pairwise(meds))


def _verdict(results: dict[str, dict[str, Any]]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for group, shifted in (("unshifted", False), ("shifted", True)):
        names = [n for n in results if n.endswith("s") == shifted]
        out[group] = {
            "igwo_paper_best": sum(_ranking(results[n])[0] == "igwo-paper" for n in names),
            "igwo_normalized_best": sum(_ranking(results[n])[0] == "igwo-normalized" for n in names),
            "paper_order_holds_with_paper_weights": sum(
                _paper_order_holds(results[n], "igwo-paper") for n in names
            ),
            "paper_order_holds_with_normalized_weights": sum(
                _paper_order_holds(results[n], "igwo-normalized") for n in names
            ),
            "functions": len(names),
        }
    u, s = out["unshifted"], out["shifted"]
    nu, ns = u["functions"], s["functions"]
    out["summary"] = (
        "Paper's ranking IGWO < GWO < WOA < GA (median final value): holds on "
        f"{u['paper_order_holds_with_paper_weights']}/{nu} unshifted functions with the literal weights "
        f"and on {s['paper_order_holds_with_paper_weights']}/{ns} shifted ones; IGWO-paper is the best "
        f"method on {u['igwo_paper_best']}/{nu} unshifted but {s['igwo_paper_best']}/{ns} shifted functions "
        "(its update pulls towards the origin); IGWO-normalized is best on "
        f"{u['igwo_normalized_best'] + s['igwo_normalized_best']}/{nu + ns}."
    )
    return out


def run(args: argparse.Namespace) -> dict[str, Any]:
    """All figures as one JSON-ready dict."""
    runners: dict[str, Runner] = dict(_runners(args.popsize, args.budget, args.dim))
    peer_note = "mealpy not installed: peer skipped"
    if not args.no_peer:
        peer = _mealpy_runner(args.popsize, args.budget)
        if peer is not None:
            runners["mealpy-gwo"] = peer
            peer_note = "mealpy GWO.OriginalGWO, same population and evaluation budget"
    else:
        peer_note = "peer skipped (--no-peer)"
    results: dict[str, dict[str, Any]] = {}
    t0 = time.perf_counter()
    for name in [n.strip() for n in args.functions.split(",") if n.strip()]:
        for shifted in (False, True):
            label = name + ("s" if shifted else "")
            results[label] = {m: _run_method(r, name, shifted, args) for m, r in runners.items()}
    return {
        "benchmark": "optim",
        "generated_utc": datetime.now(UTC).isoformat(),
        "dim": args.dim,
        "popsize": args.popsize,
        "budget_evals": args.budget,
        "seeds": args.seeds,
        "peer": peer_note,
        "units": {"fun": "objective value (dimensionless, noise-free for F7)", "wall_s": "s"},
        "functions": results,
        "ranking": {n: _ranking(m) for n, m in results.items()},
        "verdict": _verdict(results),
        "targets": [],
        "total_wall_s": time.perf_counter() - t0,
    }


def _print_tables(out: dict[str, Any]) -> None:
    print(
        f"python -m benchmarks optim  {out['generated_utc']}  dim={out['dim']} pop={out['popsize']} "
        f"budget={out['budget_evals']} evaluations, medians over {out['seeds']} seeds; {out['peer']}"
    )
    methods = list(next(iter(out["functions"].values())))
    print(f"{'function':9s}" + "".join(f"{m:>17s}" for m in methods))
    for name, res in out["functions"].items():
        print(f"{name:9s}" + "".join(f"{res[m]['fun']['median']:>17.3e}" for m in methods))
    print("median evaluations / wall time per run:")
    for name, res in out["functions"].items():
        cells = "".join(f"{int(res[m]['nfev_median']):>10d}/{res[m]['wall_s_median']:5.3f}s" for m in methods)
        print(f"{name:9s}{cells}")
    for name, order in out["ranking"].items():
        print(f"ranking {name:4s}: {' < '.join(order)}")
    print(out["verdict"]["summary"])
    print(format_verdicts(out["targets"]) + " (a comparison of methods: the ranking above is the result)")
    print(f"total {out['total_wall_s']:.1f} s")


def main(args: argparse.Namespace) -> int:
    if args.seeds < 1 or args.budget < 2 * args.popsize:
        print("error: --seeds must be >= 1 and --budget >= 2 x --popsize")
        return 2
    out = run(args)
    return report(out, as_json=args.json, table=_print_tables)
