"""Cost of one H-map identification of a 60-min window with 40 speed segments vs today's single-condition
60-min identification (``model.identify.identify``, method hybrid). A measurement script, not a test:

    OPENBLAS_NUM_THREADS=1 python -m tests.model_hmap.bench [--repeat 5] [--family nodes|physics] [--service]

The window comes from the virtual plant (1.5 mm mesh, h_true): 40 segments of 60-120 s (whole 10-s steps,
3600 s in all) at speeds drawn from 0..7000 rpm, torque 3-15 N·m; the single-condition window is 60 min at
4000 rpm, 10 N·m. Prints medians of ``--repeat`` runs of each (cold start: the empirical prior; chained:
the same window again with the first fit's posterior after 1 h of forgetting as the prior).

``--service``: the service's fit instead (docs/design/hmap.md "In the service"): the served reduced model
(rank 56, exact step; ``service.modelload``), per-channel biases (1σ 0.034 °C: a baseline's offset error and
the model error) and 6 start modes (0.1 °C along the model's first basis vectors) as nuisances, and the
chained fit starting from the first fit's θ.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from model import hmap, rom_segments
from model import hmap_identify as hi
from model.identify import Window, identify
from model.inputs import inputs_from_operation
from model.plant import Segment, VirtualPlant
from tests.model_hmap.duty import load_service_model, window


def forty_segments(seed: int) -> list[Segment]:
    rng = np.random.default_rng(seed)
    lengths = 6 + rng.multinomial(120, np.ones(40) / 40)  # steps of 10 s, 360 in all
    grid = np.arange(0.0, 7001.0, 500.0)
    speeds = [float(rng.choice(grid))]
    while len(speeds) < 40:  # consecutive speeds differ: 40 segments
        speeds.append(float(rng.choice(grid[grid != speeds[-1]])))
    return [
        Segment(10.0 * float(n), float(s), 0.0 if s == 0 else float(rng.uniform(3, 15)), 22.0)
        for n, s in zip(lengths, speeds, strict=True)
    ]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--family", choices=("nodes", "physics"), default="nodes")
    parser.add_argument("--service", action="store_true", help="the service's model and nuisances")
    args = parser.parse_args()
    extra: dict[str, object] = {}
    if args.service:
        from service.modelload import ModelRef, load_model
        from service.settings import Settings

        model = load_model(ModelRef.from_settings(Settings()))
        r = model.rom.rank
        extra = {"bias_sd_c": 0.034, "start_modes": 0.1 * np.eye(r)[:6]}
    else:
        model = load_service_model()
    spec, rom = model.spec, model.rom
    plant = VirtualPlant(spec, seed=3)
    run = plant.run(forty_segments(3), dt_s=10.0)
    w = window(spec, run, 0, 360, float(run.ambient_c[0]))
    family = hmap.Family(args.family)
    cold = family.prior(spec)
    single = plant.run([Segment(3600.0, 4000.0, 10.0, 22.0)], dt_s=10.0)
    inputs = inputs_from_operation(
        spec, dt_s=10.0, speed_rpm=single.speed_rpm[:-1], torque_nm=single.torque_nm[:-1],
        ambient_c=single.ambient_c[:-1],
    )  # fmt: skip
    w_single = Window(inputs, single.temps_c, np.ones(32, dtype=bool), 22.0, speed_rpm=4000.0)
    identify(rom, w_single, rng=0, method="hybrid", spec=spec)  # warm-up (imports, caches)
    t_map, t_chain, t_single, runs, runs_chained = [], [], [], [], []
    for i in range(args.repeat):
        started = time.perf_counter()
        fit = hi.identify_map(rom, w, cold, family=family, **extra)  # type: ignore[arg-type]
        t_map.append(time.perf_counter() - started)
        runs.append(fit.nfev)
        prior = hi.forget(fit.posterior, cold, elapsed_h=1.0)
        started = time.perf_counter()
        x0 = fit.posterior.mean if args.service else None
        chained = hi.identify_map(rom, w, prior, family=family, x0=x0, **extra)  # type: ignore[arg-type]
        runs_chained.append(chained.nfev)
        t_chain.append(time.perf_counter() - started)
        started = time.perf_counter()
        identify(rom, w_single, rng=i, method="hybrid", spec=spec)
        t_single.append(time.perf_counter() - started)
    out = {
        "family": args.family,
        "service": bool(args.service),
        "rom_rank": int(rom.rank),
        "segments": rom_segments.plan_from_speed(w.speed_rpm).n_segments,
        "map_cold_s_median": round(float(np.median(t_map)), 3),
        "map_chained_s_median": round(float(np.median(t_chain)), 3),
        "single_hybrid_s_median": round(float(np.median(t_single)), 3),
        "ratio_cold": round(float(np.median(t_map) / np.median(t_single)), 2),
        "ratio_chained": round(float(np.median(t_chain) / np.median(t_single)), 2),
        "model_runs_cold_median": float(np.median(runs)),
        "model_runs_chained_median": float(np.median(runs_chained)),
    }
    print(json.dumps(out))


if __name__ == "__main__":
    main()
