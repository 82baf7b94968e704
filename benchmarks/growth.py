"""``python -m benchmarks growth``: the served thermal growth against the virtual plant's own growth.

Data are SYNTHETIC. Per seed the virtual plant (finer mesh, its own truth ``model.plant.h_true``,
σ = 0.15 °C noise) runs a profile and keeps its full field every ``--every-s``; its growth comes from a growth
model built on the *plant's* mesh (``model.thermoelastic``), so mesh and time discretisation differ from the
service's. The samples go through the service's own core, sample by sample, exactly as
``service.core.offline.run_offline`` feeds them (``ServiceCore.ingest``, identifications inline with the
same seeded worker function). At every ``--every-s`` after the first successful identification the bench
asks the service's own ``service.serve.compensation.GrowthServer`` (as ``/compensation`` does) for the growth
of the core's view, so everything is the service's real path:

- the field and its uncertainty: the filtered live state now (``field_belief``: the Kalman filter's reduced
  mean and covariance, ``service.estimate.state``; the covariance holds the considered H error);
- H: the live state's H; Σ_H from the current identification record's CIs (``h_covariance``: uncorrelated,
  as stored; in speed-map mode the map's posterior at the live speed, ``map_h_covariance``); the condition:
  the detector's current condition (held).

``--mode per_condition|speed_map|combined`` and ``--set KEY=VALUE`` choose the identification mode and
settings (``benchmarks.identmode``; default: the settings'), reported as ``mode``.

Profiles: ``chain`` (the chain bench's: idle,
3000/4000/5000 rpm for 45 min each) and ``duty`` (5 min idle, 45 min at 4000 rpm so that an identification
exists, then 90 min of speed changes every 1-6 min, 0-7000 rpm, torque 3-15 N·m, ambient drifting ±1 °C;
seeded). The plant has its own mechanics (``--plant-mechanics drawn``, the default: per seed a mount restraint
between free and held and α factors within ±5 %, ``model.plantmech``; the service keeps its TOML's;
``nominal``: the plant shares them). The reference temperature is the plant's uniform start (the controller
is zeroed cold).

Figures: |axial error| median and max [µm], 95 % CI coverage (axial, radial), the steady-state forecast's
coverage at the end of every held condition (≥ 30 min), the forecast's error at 5/15/30 min where the plant's
condition holds over the horizon, and the cost of one evaluation (the served dot products, and the whole
``estimate_growth``; median of repeats).
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import UTC, datetime
from typing import Any

import numpy as np

from benchmarks import identmode
from benchmarks.chain import PROFILE as CHAIN
from benchmarks.chain import T0
from benchmarks.compensation_run import add_plant_mechanics_argument
from benchmarks.targets import Target, format_verdicts, report, verdicts
from service.serve.compensation import GrowthServer

DT_S = 10.0
HORIZON_STEPS = (30, 90, 180)  # 5, 15, 30 min of 10-s samples
TARGETS = (
    Target("axial_err_um_median", "<=", 2.0, unit="µm"),
    Target("coverage", "in", (0.85, 1.0), note="axial, every evaluation after the first identification"),
    Target("steady_forecast_covered", ">=", 0.85, note="end of every held condition (>= 30 min)"),
    Target("eval_ms", "<=", 0.1, unit="ms", note="the served growth from the live field (dot products)"),
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``python -m benchmarks growth``."""
    parser.add_argument("--seeds", type=int, default=3, help="virtual-plant seeds per profile (default 3)")
    parser.add_argument(
        "--profiles", default="chain,duty", help="comma-separated: chain, duty (default both)"
    )
    parser.add_argument("--every-s", type=float, default=60.0, help="evaluation period [s] (default 60)")
    add_plant_mechanics_argument(parser)
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    identmode.add_arguments(parser)


def duty_profile(seed: int) -> tuple[tuple[float, float, float, float], ...]:
    """5 min idle, 45 min at 4000 rpm, then 90 min of random segments (seeded): 1-6 min each, 0-7000 rpm,
    3-15 N·m, ambient 22 °C ± 1 °C drifting (a sine of random phase and a 1.5-3 h period)."""
    rng = np.random.default_rng(10_000 + seed)
    amb0, period, phase = 22.0, rng.uniform(5400.0, 10800.0), rng.uniform(0.0, 2 * np.pi)
    out = [(300.0, 0.0, 0.0, amb0), (2700.0, 4000.0, 6.0, amb0)]
    t = 3000.0
    while t < 3000.0 + 5400.0:
        dur = float(np.round(rng.uniform(60.0, 360.0) / DT_S) * DT_S)
        amb = amb0 + np.sin(2 * np.pi * t / period + phase)
        out.append((dur, float(np.round(rng.uniform(0.0, 7000.0), -2)), float(rng.uniform(3.0, 15.0)), amb))
        t += dur
    return tuple((d, s, q, round(float(a), 2)) for d, s, q, a in out)


@dataclass
class _Rows:
    """Per evaluation point: truth and served values (µm)."""

    axial_err: list[float] = field(default_factory=list)
    radial_err: list[float] = field(default_factory=list)
    axial_in: list[bool] = field(default_factory=list)
    radial_in: list[bool] = field(default_factory=list)
    half_width: list[float] = field(default_factory=list)
    z: list[float] = field(default_factory=list)  # axial error / served 1σ
    steady_in: list[bool] = field(default_factory=list)
    steady_err: list[float] = field(default_factory=list)
    horizon_err: dict[int, list[float]] = field(default_factory=lambda: {n: [] for n in HORIZON_STEPS})
    horizon_in: dict[int, list[bool]] = field(default_factory=lambda: {n: [] for n in HORIZON_STEPS})
    eval_s: list[float] = field(default_factory=list)
    estimate_s: list[float] = field(default_factory=list)


class _Plant:
    """The plant's mesh, its growth model and its steady growth per condition (cached).

    ``mechanics`` "drawn" (default): each seed's plant has its own mechanics
    (``model.plantmech.mechanics_for_seed``), unknown to the service; "nominal": the description's own."""

    def __init__(self, spec: Any, *, mechanics: str = "drawn") -> None:
        from model.fem import build_fe_model

        if mechanics not in ("drawn", "nominal"):
            raise ValueError(f"--plant-mechanics: must be drawn or nominal, got {mechanics!r}")
        self.spec = spec
        self.mode = mechanics
        self.fe = build_fe_model(spec, mesh_size_m=spec.plant_mesh_size_m)
        self.growth: Any = None
        self.rows: list[int] = []
        self.seed: int | None = None
        self._steady: dict[tuple[float, float, float], np.ndarray] = {}

    def use(self, seed: int) -> None:
        """Build the growth model of seed ``seed``'s plant mechanics (once per seed in a row)."""
        from model.plantmech import PlantMechanics, build_plant_growth, mechanics_for_seed

        if self.seed == seed and self.growth is not None:
            return
        mech = mechanics_for_seed(seed) if self.mode == "drawn" else PlantMechanics.nominal(self.spec)
        self.growth = build_plant_growth(self.spec, self.fe, mech)
        self.rows = [self.growth.names.index(n) for n in ("nose_axial", "nose_radial")]
        self.seed = seed

    def run(self, profile: Any, seed: int, every: int) -> Any:
        from model.plant import Segment, VirtualPlant

        self.use(seed)
        plant = VirtualPlant(self.spec, seed=seed, fe=self.fe, growth=self.growth)
        return plant.run([Segment(*s) for s in profile], dt_s=DT_S, keep_fields_every=every)

    def growth_um(self, field_c: np.ndarray, t_ref_c: float) -> np.ndarray:
        return np.asarray(self.growth.growth_um(field_c, t_ref_c)[self.rows])

    def steady_um(self, speed: float, torque: float, ambient: float, t_ref_c: float) -> np.ndarray:
        from model.fem import steady_state
        from model.inputs import inputs_from_operation
        from model.plant import h_true

        key = (speed, torque, ambient)
        if key not in self._steady:
            inp = inputs_from_operation(
                self.spec, dt_s=DT_S, speed_rpm=speed, torque_nm=torque, ambient_c=ambient
            )
            self._steady[key] = steady_state(
                self.fe,
                h_true(speed, ambient, torque),
                ambient_c=ambient,
                q_front_w=float(inp.q_front_w[0]),
                q_rear_w=float(inp.q_rear_w[0]),
            )
        return self.growth_um(self._steady[key], t_ref_c)


def serve_offline(
    samples: list[Any], model: Any, config: Any, on_sample: Callable[[Any, int, Any], None]
) -> None:
    """The service's core offline (``service.core.offline.run_offline``: the same events and job outcomes),
    calling ``on_sample(core, k, last_ok_result)`` after sample k and its identifications, so that the live
    state can be read as the service would serve it."""
    from service.core.offline import run_offline

    run_offline(samples, model=model, config=config, on_sample=on_sample)


class _Evaluator:
    """Evaluates the served growth at the chosen samples of one run and compares it with the plant's."""

    def __init__(
        self, *, model: Any, ctx: Any, plant: _Plant, run: Any, samples: list[Any], every: int
    ) -> None:
        self.model, self.ctx, self.plant, self.run, self.every = model, ctx, plant, run, every
        self.samples = samples
        self.t_ref = float(run.truth_c[0].mean()) if run.fields_c.size == 0 else float(run.fields_c[0].mean())
        self.rows = _Rows()
        self.last_terms: Any = None
        # the service's own server (service.serve.compensation): its terms, field belief and Σ_H
        self.server = GrowthServer(model, t_ref_c=self.t_ref, context=ctx)
        cond = np.column_stack([run.speed_rpm, run.torque_nm, run.ambient_c])
        self.cond = cond
        # last sample of each held condition >= 30 min: where the steady forecast is checked
        change = np.flatnonzero(np.any(np.diff(cond, axis=0) != 0, axis=1)) + 1
        starts, ends = np.r_[0, change], np.r_[change - 1, len(cond) - 1]
        self.checkpoints = {
            int(e - (e % every)) for s, e in zip(starts, ends, strict=True) if e - s >= HORIZON_STEPS[-1]
        }

    def __call__(self, core: Any, k: int, result: Any) -> None:
        from service.serve.compensation import field_belief

        view = core.view()
        if result is None or k % self.every or view.live is None or view.current is None:
            return
        ready = self.server.ready_for(view)  # else this call computes the condition terms first
        started = time.perf_counter()
        est = self.server.estimate(view)
        if ready:
            self.rows.estimate_s.append(time.perf_counter() - started)
        if est is None:
            return
        self.last_terms = self.server.refresh(view)  # cached: the terms est used
        belief = field_belief(view)
        started = time.perf_counter()
        _ = self.ctx.g_phi @ belief.state if self.ctx.g_phi is not None else self.ctx.g @ view.live.field_c
        self.rows.eval_s.append(time.perf_counter() - started)
        self._compare(k, est)

    def _compare(self, k: int, est: Any) -> None:
        run, r = self.run, self.rows
        truth = self.plant.growth_um(run.fields_c[k // self.every], self.t_ref)
        for value, t, err, inside in (
            (est.axial, truth[0], r.axial_err, r.axial_in),
            (est.radial, truth[1], r.radial_err, r.radial_in),
        ):
            err.append(value.um - t)
            inside.append(value.ci95_um[0] <= t <= value.ci95_um[1])
        r.half_width.append(0.5 * (est.axial.ci95_um[1] - est.axial.ci95_um[0]))
        if est.axial.std_um > 0:
            r.z.append((est.axial.um - truth[0]) / est.axial.std_um)
        if k in self.checkpoints:
            speed, torque, amb = (float(v) for v in self.cond[k])
            ss = self.plant.steady_um(speed, torque, amb, self.t_ref)[0]
            lo, hi = est.forecast.steady_axial.ci95_um
            r.steady_in.append(lo <= ss <= hi)
            r.steady_err.append(est.forecast.steady_axial.um - ss)
        for i, n in enumerate(HORIZON_STEPS):
            j = k + n
            if j >= len(self.cond) or np.any(self.cond[k:j] != self.cond[k]):
                continue
            t = self.plant.growth_um(run.fields_c[j // self.every], self.t_ref)[0]
            v = est.forecast.axial[i]
            r.horizon_err[n].append(v.um - t)
            r.horizon_in[n].append(v.ci95_um[0] <= t <= v.ci95_um[1])


def _stats(values: list[float]) -> dict[str, float | None]:
    a = np.abs(np.asarray(values, dtype=float))
    if a.size == 0:
        return {"median": None, "max": None, "n": 0}
    return {"median": round(float(np.median(a)), 3), "max": round(float(a.max()), 3), "n": int(a.size)}


def _frac(values: list[bool]) -> float | None:
    return round(float(np.mean(values)), 3) if values else None


def summarise(r: _Rows) -> dict[str, Any]:
    """The figures of one set of rows."""
    ax, rad = _stats(r.axial_err), _stats(r.radial_err)
    return {
        "axial_err_um_median": ax["median"],
        "axial_err_um_max": ax["max"],
        "radial_err_um_median": rad["median"],
        "radial_err_um_max": rad["max"],
        "coverage": _frac(r.axial_in),
        "radial_coverage": _frac(r.radial_in),
        "ci_half_width_um_median": None if not r.half_width else round(float(np.median(r.half_width)), 3),
        # 0.674 for a calibrated Gaussian 1σ; lower: the CI is wider than the errors need
        "err_over_std_median": None if not r.z else round(float(np.median(np.abs(r.z))), 3),
        "steady_forecast_covered": _frac(r.steady_in),
        "steady_forecast_err_um": _stats(r.steady_err),
        "forecast_err_um": {f"{n * DT_S / 60:.0f}min": _stats(r.horizon_err[n]) for n in HORIZON_STEPS},
        "forecast_coverage": {f"{n * DT_S / 60:.0f}min": _frac(r.horizon_in[n]) for n in HORIZON_STEPS},
        "evaluations": ax["n"],
    }


def _merge(rows: list[_Rows]) -> _Rows:
    out = _Rows()
    for r in rows:
        for name in (
            "axial_err",
            "radial_err",
            "z",
            "axial_in",
            "radial_in",
            "half_width",
            "steady_in",
            "steady_err",
            "eval_s",
            "estimate_s",
        ):
            getattr(out, name).extend(getattr(r, name))
        for n in HORIZON_STEPS:
            out.horizon_err[n].extend(r.horizon_err[n])
            out.horizon_in[n].extend(r.horizon_in[n])
    return out


def _profile(name: str, seed: int) -> tuple[tuple[float, float, float, float], ...]:
    if name == "chain":
        return CHAIN
    if name == "duty":
        return duty_profile(seed)
    raise ValueError(f"--profiles: unknown profile {name!r} (chain, duty)")


def _eval_cost(ctx: Any, terms: Any, belief: Any, t_ref: float, repeats: int = 300) -> tuple[float, float]:
    """Median [ms] of the served dot products and of the whole ``estimate_growth``."""
    from service.estimate.growth import estimate_growth

    at = datetime.now(UTC)
    dots, whole = [], []
    for _ in range(repeats):
        t = time.perf_counter()
        _ = ctx.g @ belief.mean_c - ctx.g.sum(axis=1) * t_ref
        dots.append(time.perf_counter() - t)
        t = time.perf_counter()
        estimate_growth(ctx, terms, belief, t_ref_c=t_ref, at=at)
        whole.append(time.perf_counter() - t)
    return 1e3 * float(np.median(dots)), 1e3 * float(np.median(whole))


def run(
    seeds: int,
    profiles: list[str],
    every_s: float,
    *,
    ident_mode: str | None = None,
    overrides: dict[str, Any] | None = None,
    progress: Any = None,
    plant_mechanics: str = "drawn",
) -> dict[str, Any]:
    from service.estimate.growth import build_context
    from service.host.runtime import core_config
    from service.modelload import ModelRef, load_model
    from simulator.plantsamples import samples_from_plant

    every = round(every_s / DT_S)
    if every < 1 or any(n % every for n in HORIZON_STEPS):
        raise ValueError(f"--every-s: must be a multiple of {DT_S:g} s dividing 5 min, got {every_s}")
    settings = identmode.bench_settings(ident_mode, overrides)
    model = load_model(ModelRef.from_settings(settings))
    config = core_config(settings)
    started = time.perf_counter()
    ctx = build_context(model.spec, model.fe, basis=model.rom.basis)
    plant = _Plant(model.spec, mechanics=plant_mechanics)
    per: dict[str, list[_Rows]] = {}
    last: _Evaluator | None = None
    for name in profiles:
        for seed in range(seeds):
            plant_run = plant.run(_profile(name, seed), seed, every)
            samples = samples_from_plant(plant_run, t0_s=T0)
            ev = _Evaluator(model=model, ctx=ctx, plant=plant, run=plant_run, samples=samples, every=every)
            serve_offline(samples, model, config, ev)
            per.setdefault(name, []).append(ev.rows)
            last = ev if ev.last_terms is not None else last
            if progress is not None:
                progress(f"{name} seed {seed + 1}/{seeds} done ({time.perf_counter() - started:.0f} s)")
    out: dict[str, Any] = {
        "synthetic": True,
        "mode": settings.identification.mode,
        "settings": overrides or {},
        "seeds": seeds,
        "plant_mechanics": plant_mechanics,
        "every_s": every * DT_S,
    }
    out |= summarise(_merge([r for rows in per.values() for r in rows]))
    out["profiles"] = {name: summarise(_merge(rows)) for name, rows in per.items()}
    eval_ms = estimate_ms = None
    if last is not None:
        from service.estimate.growth import FieldBelief

        belief = FieldBelief(mean_c=np.asarray(last.last_terms.t_ss), includes_h=False)
        eval_ms, estimate_ms = _eval_cost(ctx, last.last_terms, belief, last.t_ref)
    out["eval_ms"] = None if eval_ms is None else round(eval_ms, 4)
    out["estimate_ms"] = None if estimate_ms is None else round(estimate_ms, 4)
    out["targets"] = verdicts(
        TARGETS,
        {k: out.get(k) for k in ("axial_err_um_median", "coverage", "steady_forecast_covered", "eval_ms")},
    )
    out["wall_s"] = round(time.perf_counter() - started, 1)
    return out


def _print(out: dict[str, Any]) -> None:
    print(
        f"served growth vs the plant's (plant mesh), synthetic, {out['seeds']} seeds per profile, "
        f"wall {out['wall_s']} s"
    )
    for name, b in [("all", out), *out["profiles"].items()]:
        print(f"\n[{name}] {b['evaluations']} evaluations")
        print(
            f"  axial |error| median {b['axial_err_um_median']} µm, max {b['axial_err_um_max']} µm; "
            f"95 % CI coverage {b['coverage']} (median half-width {b['ci_half_width_um_median']} µm, "
            f"median |error|/σ {b['err_over_std_median']})"
        )
        print(
            f"  radial |error| median {b['radial_err_um_median']} µm, max {b['radial_err_um_max']} µm; "
            f"coverage {b['radial_coverage']}"
        )
        ss = b["steady_forecast_err_um"]
        print(
            f"  steady forecast covered {b['steady_forecast_covered']} "
            f"(|error| median {ss['median']} max {ss['max']} µm, n {ss['n']})"
        )
        for h, s in b["forecast_err_um"].items():
            print(
                f"  forecast +{h}: |error| median {s['median']} max {s['max']} µm (n {s['n']}), "
                f"coverage {b['forecast_coverage'][h]}"
            )
    print(
        f"\none evaluation: served dot products {out['eval_ms']} ms, "
        f"whole estimate_growth {out['estimate_ms']} ms"
    )
    print(format_verdicts(out["targets"]))


def main(args: argparse.Namespace) -> int:
    if args.seeds < 1:
        print("error: --seeds must be >= 1", file=sys.stderr)
        return 2
    profiles = [p.strip() for p in str(args.profiles).split(",") if p.strip()]
    try:
        out = run(
            args.seeds,
            profiles,
            float(args.every_s),
            ident_mode=args.ident_mode,
            overrides=identmode.parse_sets(args.set),
            progress=lambda m: print(m, file=sys.stderr, flush=True),
            plant_mechanics=str(args.plant_mechanics),
        )
    except ValueError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    return report(out, as_json=args.json, table=_print)
