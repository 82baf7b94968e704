"""Cost of one estimator sample (predict + update with 32 channels) on a reduced model.

Run (reads or builds the reduced model in the cache directory, as the service does; prints the median over
the runs of the mean time per sample [ms], plus the field-σ and convergence-test costs)::

    OPENBLAS_NUM_THREADS=1 python -m benchmarks.studies.estimator_bench [--rank 46] [--cache-dir D] [--runs 7]
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path
from typing import Any

import numpy as np

from model.estimator import NisWindow, StateEstimator, StepInput, convergence, wide_prior
from model.rom import DEFAULT_RANK


def bench_step(rom: Any, *, runs: int = 7, steps: int = 360, seed: int = 0) -> dict[str, float]:
    """Median over ``runs`` of the mean wall (and CPU) time [ms] per sample of ``StateEstimator.step`` (H
    fixed, its transition cached as in the service; inputs changing every step; one channel masked), of
    ``field_std`` over all nodes and of ``convergence``."""
    rng = np.random.default_rng(seed)
    h = np.array([88.0, 46.0, 68.0, 47.0, 52.0, 70.0, 17.0])
    mask = np.ones(32, dtype=bool)
    mask[6] = False
    meas = 25.0 + rng.normal(0.0, 0.15, (steps, 32))
    step_ms, step_cpu_ms, std_ms, conv_ms = [], [], [], []
    for _ in range(runs):
        est = StateEstimator(rom, wide_prior(rom, ambient_c=22.0))
        est.transition(h, 10.0)  # the service computes it once per new H
        window = NisWindow(60)
        started, cpu = time.perf_counter(), time.process_time()
        for k in range(steps):
            res = est.step(StepInput(h, 22.0 + 1e-3 * k, 120.0 + 0.1 * k, 60.0), meas[k], mask)
            window.push(res.nis, res.dof)
        step_ms.append((time.perf_counter() - started) * 1e3 / steps)
        step_cpu_ms.append((time.process_time() - cpu) * 1e3 / steps)
        started = time.perf_counter()
        est.field_std()
        std_ms.append((time.perf_counter() - started) * 1e3)
        started = time.perf_counter()
        convergence(rom, est.estimate, window)
        conv_ms.append((time.perf_counter() - started) * 1e3)
    return {
        "rank": float(rom.k0.shape[0]),
        "step_ms": statistics.median(step_ms),
        "step_ms_max_run": max(step_ms),
        "step_cpu_ms": statistics.median(step_cpu_ms),
        "field_std_ms": statistics.median(std_ms),
        "convergence_ms": statistics.median(conv_ms),
        "transition_ms": _time_transition(rom, h),
    }


def _time_transition(rom: Any, h: np.ndarray) -> float:
    """Median [ms] of building a new transition (eigendecomposition of K_r(H)), i.e. the cost of a new H."""
    est = StateEstimator(rom, wide_prior(rom, ambient_c=22.0), cache_size=1)
    times = []
    for i in range(7):
        started = time.perf_counter()
        est.transition(h * (1.0 + 0.01 * (i + 1)), 10.0)
        times.append((time.perf_counter() - started) * 1e3)
    return statistics.median(times)


def main(argv: list[str] | None = None) -> None:
    """Load (or build) the packaged spindle's reduced model and print the estimator's cost per sample."""
    from model.fem import build_fe_model
    from model.geometry import load_spindle
    from model.rom import load_or_build_rom

    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--rank", type=int, default=DEFAULT_RANK)
    parser.add_argument("--cache-dir", type=Path, default=Path.home() / ".cache" / "spindle-chtc")
    parser.add_argument("--runs", type=int, default=7)
    args = parser.parse_args(argv)
    spec = load_spindle()
    fe = build_fe_model(spec)
    args.cache_dir.mkdir(parents=True, exist_ok=True)
    rom = load_or_build_rom(fe, spec, args.cache_dir, rank=args.rank)
    out = bench_step(rom, runs=args.runs)
    print(
        f"estimator, rank {int(out['rank'])}, N {fe.n_nodes}: step (predict + update) {out['step_ms']:.3f} ms"
        f" per sample wall, {out['step_cpu_ms']:.3f} ms CPU (medians of {args.runs} runs of 360 samples;"
        f" slowest run {out['step_ms_max_run']:.3f} ms wall); new H {out['transition_ms']:.3f} ms;"
        f" field 1σ all nodes {out['field_std_ms']:.3f} ms; convergence test {out['convergence_ms']:.3f} ms"
    )


if __name__ == "__main__":
    main()
