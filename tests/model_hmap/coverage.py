"""Coverage of the H map over seeded duty cycles on the virtual plant (not a test: a measurement script).

    OPENBLAS_NUM_THREADS=1 python -m tests.model_hmap.coverage --seeds 0 1 2 3 4 [--json]

Per seed: a 2-h duty cycle (speed changes every 1-6 min among 0..7000 rpm, torque 3-15 N·m, ambient ±1 °C)
on ``model.plant.VirtualPlant`` (1.5 mm mesh, its own ``h_true``); window 1 (0-60 min) is fitted from the
cold-start prior, window 2 (60-120 min) from window 1's posterior after ``forget`` (1 h) with window 1's
fitted end field as its start. At every speed a window visited, H and its band are compared with h_true at
the window's mean ambient: median |error| per H, coverage per H (Laplace band,
the family chosen by --family), median band half-width, wall times, and whether window 2's band at
window 1's speeds is narrower than window 1's.
"""

from __future__ import annotations

import argparse
import json
import time
from typing import Any

import numpy as np

from model import hmap
from model import hmap_identify as hi
from model.plant import VirtualPlant, h_true
from tests.model_hmap.duty import load_service_model, run_duty, window


def score(fit: hi.MapFit, run: Any, k0: int, k1: int) -> dict[str, Any]:
    """Errors and band checks at the speeds visited in samples k0..k1 (per visited speed and zone)."""
    speeds = np.unique(run.speed_rpm[k0:k1])
    amb = float(np.mean(run.ambient_c[k0:k1]))
    p, fam = fit.posterior, fit.family
    h = fam.h_at(p.mean, speeds, amb)
    sd = fam.log_h_sd(p.mean, p.cov, speeds, amb)
    truth = np.array([h_true(float(s), amb) for s in speeds])
    return {
        "err": np.abs(h / truth - 1.0),
        "inside": np.abs(np.log(h / truth)) <= hmap.Z95 * sd,
        "half": np.exp(hmap.Z95 * sd) - 1.0,
        "sd_median": float(np.median(sd)),
    }


def one_seed(model: Any, seed: int, family: hmap.Family) -> dict[str, Any]:
    plant = VirtualPlant(model.spec, seed=seed)
    run = run_duty(plant, seed, duration_s=7200.0).run
    cold = family.prior(model.spec)
    w1 = window(model.spec, run, 0, 360, float(run.ambient_c[0]))
    f1 = hi.identify_map(model.rom, w1, cold, family=family)
    prior2 = hi.forget(f1.posterior, cold, elapsed_h=1.0)
    w2 = window(model.spec, run, 360, 720, f1.end_field_c)
    f2 = hi.identify_map(model.rom, w2, prior2, family=family)
    s1, s2 = score(f1, run, 0, 360), score(f2, run, 0, 360)  # same speeds: does chaining narrow the band?
    return {
        "w1": s1,
        "w2": score(f2, run, 360, 720),
        "wall_s": (f1.wall_s, f2.wall_s),
        "runs": (f1.nfev, f2.nfev),
        "narrower": s2["sd_median"] < s1["sd_median"],
    }


def summary(results: list[dict[str, Any]], key: str) -> dict[str, list[float]]:
    def cat(name: str) -> Any:
        return np.vstack([r[key][name] for r in results])

    return {
        "h_err_pct_median": np.round(100 * np.median(cat("err"), axis=0), 1).tolist(),
        "coverage": np.round(cat("inside").mean(axis=0), 2).tolist(),
        "band_half_width_pct_median": np.round(100 * np.median(cat("half"), axis=0), 1).tolist(),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4])
    parser.add_argument("--family", choices=("nodes", "physics"), default="nodes")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    model = load_service_model()
    started = time.perf_counter()
    family = hmap.Family(args.family)
    results = [one_seed(model, s, family) for s in args.seeds]
    walls = np.array([r["wall_s"] for r in results])
    out = {
        "seeds": args.seeds,
        "window1_cold": summary(results, "w1"),
        "window2_chained": summary(results, "w2"),
        "identify_wall_s_median": np.round(np.median(walls, axis=0), 2).tolist(),
        "identify_wall_s_max": np.round(walls.max(axis=0), 2).tolist(),
        "model_runs_median": np.median([r["runs"] for r in results], axis=0).tolist(),
        "chained_narrower_fraction": float(np.mean([r["narrower"] for r in results])),
        "family": args.family,
        "total_s": round(time.perf_counter() - started, 1),
    }
    print(json.dumps(out) if args.json else json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
