"""``python -m benchmarks commission``: the product's commissioning against the literature's peer, side by
side (issue 27 item 4).

Data are SYNTHETIC. Per seed the plant draws its own mechanics (``model.plantmech``, unknown to the service)
and its own H(speed) truth (``simulator.randomtruth``, the same in its test and its duty cycle: one machine)
and runs the simulated ISO 230-3 thermal test (``simulator.thermaltest``: temperatures, CAN log,
displacements with noise, fixture offset, drift and missing readings). On that one test:

- the product commissions (``service.shell.commissioning.commission_growth``, the service's own core);
- the peer fits an MLR (``benchmarks.studies.mlr``: 4–6 sensors by correlation clustering, least squares of
  the measured axial displacement on their temperatures plus an intercept).

Then on a separate duty cycle of the same plant (``simulator.duty``, the seed's H(speed) truth,
per-channel offsets ±0.2 °C: ``benchmarks.compensation_run.Plant``), every
minute after the rest, the axial error against the plant's true growth (over its cold uniform start):

- ``none``: no compensation (the error is the growth itself);
- ``mlr``: the MLR's prediction minus its prediction at the first sample (zeroed cold, as the controller is);
- ``uncalibrated``, ``calibrated``, ``probe``: the product as it serves ``/compensation``
  (``serve_duty``: the service's shell, core, inline identification and growth server on a manual clock,
  zeroed at the first rest in equilibrium, its policy's verdict) without a commissioning, with the
  commissioned mechanics, and with them plus a probe reading (the true growth + N(0, ``--probe-sd-um``²))
  every ``--probe-min`` after the rest posted as ``POST /compensation/measurements`` does
  (``add_measurement``); each minute's row is the one served before that minute's reading. Each of the
  three restarts half-way through the machining with what its database holds (``compensation_run.
  stored_state``, the commissioning and the accepted probe readings replayed).

Figures per method, pooled over the seeds: |error| median, p95, max and RMS [µm] over the minutes the
method served a value, and ``removed`` (1 − RMS / RMS without compensation). For the product also the 95 %
CI's coverage of the truth (served minutes), ``usable_fraction`` (the policy's ``usable_for_compensation``
over all minutes after the rest) and ``err_um_p95_usable`` (the minutes a controller would apply).
``rms_ratio_calibrated_over_mlr`` per seed compares both over the minutes the calibrated product served.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.compensation_run import add_jobs_argument
from service.contracts.probe import ProbeError

Z95 = 1.959963984540054
METHODS = ("none", "mlr", "uncalibrated", "calibrated", "probe")
PRODUCT = ("calibrated", "uncalibrated", "probe")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``python -m benchmarks commission``."""
    parser.add_argument("--seeds", type=int, default=3, help="drawn plants (default 3)")
    parser.add_argument("--first-seed", type=int, default=0, help="first seed, default 0")
    parser.add_argument("--hours", type=float, default=2.5, help="duty cycle length incl. the rest (2.5 h)")
    parser.add_argument("--rest-min", type=int, default=30, help="rest before machining, min (30)")
    parser.add_argument("--short", action="store_true", help="the 80-min thermal test instead of the 4-h one")
    parser.add_argument("--sensors", type=int, default=5, help="MLR sensors (clusters), 4-6 (default 5)")
    parser.add_argument("--probe-min", type=float, default=60.0, help="probe reading period, min (60)")
    parser.add_argument("--probe-sd-um", type=float, default=1.0, help="probe reading 1σ, µm (1)")
    add_jobs_argument(parser)
    parser.add_argument("--json", action="store_true", help="print one JSON object")


def read_axial(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """The displacement CSV's times [epoch s] and axial readings [µm] (NaN where missing)."""
    from datetime import datetime

    t, a = [], []
    for line in path.read_text(encoding="utf-8").splitlines():
        if not line or line.startswith("#") or line.startswith("time"):
            continue
        stamp, axial, _ = line.split(",")
        t.append(datetime.fromisoformat(stamp.replace("Z", "+00:00")).timestamp())
        a.append(float(axial) if axial else float("nan"))
    return np.array(t), np.array(a)


def fit_peer(temperatures: Path, displacements: Path, *, n_sensors: int) -> Any:
    """The MLR on a thermal test's files: each displacement reading against the temperature row at or
    before it."""
    from benchmarks.studies.mlr import fit_mlr
    from drivers.logs import read_temperature_csv

    log = read_temperature_csv(temperatures)
    td, axial = read_axial(displacements)
    k = np.clip(np.searchsorted(log.t_s, td + 1e-6, side="right") - 1, 0, log.n_rows - 1)
    return fit_mlr(log.temps_c[k], axial, n_clusters=n_sensors)


@dataclass(frozen=True)
class PreparedSeed:
    """One seed's thermal test (commissioned, and the MLR peer fitted on it) and its duty cycle (the plant's
    run, its true axial growth [µm], the samples as the service reads them, the restart's sample)."""

    mech: Any
    report: Any
    peer: Any
    fit_s: float
    mlr_s: float
    run: Any
    truth: Any
    samples: list[Any]
    restart_k: int


def prepare_seed(model: Any, settings: Any, plant: Any, seed: int, args: argparse.Namespace) -> PreparedSeed:
    """The seed's plant mechanics, thermal test, commissioning, MLR fit and duty cycle (module docstring)."""
    from benchmarks.compensation_run import PER_MIN, T0
    from model.plant import VirtualPlant
    from service.estimate.mechanics import served_mechanics_basis
    from service.host.runtime import core_config
    from simulator.duty import duty_profile
    from simulator.plantsamples import samples_from_plant
    from simulator.randomtruth import draw_truth
    from simulator.thermaltest import RECOMMENDED_PROFILE, SHORT_PROFILE, write_thermal_test

    config = core_config(settings)
    basis = served_mechanics_basis(model.spec, model.fe)
    mech = plant.mechanics(seed)
    # one machine: its test and its duty cycle share the seed's drawn H(speed) truth (the test's H was the
    # paper's law, model.plant.h_true, for every seed until 2026-11-28)
    truth_h = draw_truth(np.random.default_rng([seed, 7]))
    test_plant = VirtualPlant(
        plant.spec, fe=plant.fe, seed=seed, mechanics=mech, growth=plant.growth(seed), h_law=truth_h
    )
    with tempfile.TemporaryDirectory(prefix="chtc-bench-commission-") as tmp:
        profile = SHORT_PROFILE if args.short else RECOMMENDED_PROFILE
        t = write_thermal_test(Path(tmp), mechanics=mech, profile=profile, seed=seed, plant=test_plant)
        started = time.perf_counter()
        rep = t.commission(model, config, basis=basis, set_by="bench")
        fit_s = time.perf_counter() - started
        started = time.perf_counter()
        peer = fit_peer(t.temperatures, t.displacements, n_sensors=args.sensors)
        mlr_s = time.perf_counter() - started

    total_min = round(60.0 * args.hours)
    duty = duty_profile(seed, duration_s=60.0 * total_min, idle_s=60.0 * args.rest_min)
    run, truth = plant.run(seed, "offsets", duty, truth_h)
    return PreparedSeed(
        mech=mech,
        report=rep,
        peer=peer,
        fit_s=fit_s,
        mlr_s=mlr_s,
        run=run,
        truth=truth,
        samples=samples_from_plant(run, t0_s=T0),
        restart_k=PER_MIN * (args.rest_min + (total_min - args.rest_min) // 2),
    )


def run_seed(model: Any, settings: Any, plant: Any, seed: int, args: argparse.Namespace) -> dict[str, Any]:
    """One seed: the thermal test, both fits, the duty cycle served three times (module docstring)."""
    from benchmarks.compensation_run import PER_MIN

    prep = prepare_seed(model, settings, plant, seed, args)
    mech, rep, peer, run, truth = prep.mech, prep.report, prep.peer, prep.run, prep.truth
    samples, restart_k = prep.samples, prep.restart_k
    served = {
        "uncalibrated": serve_duty(model, settings, samples, run, truth, restart_k=restart_k),
        "calibrated": serve_duty(
            model, settings, samples, run, truth, restart_k=restart_k, mechanics=rep.calibration
        ),
        "probe": serve_duty(
            model,
            settings,
            samples,
            run,
            truth,
            restart_k=restart_k,
            mechanics=rep.calibration,
            probe=ProbePlan(
                every_min=args.probe_min,
                after_min=args.rest_min,
                sd_um=args.probe_sd_um,
                rng=np.random.default_rng([seed, 11]),
            ),
        ),
    }
    mlr_pred = peer.predict(run.temps_c)
    keep = [i for i, tt in enumerate(run.field_times_s) if tt >= 60.0 * args.rest_min]
    err: dict[str, list[float]] = {
        "none": [float(-truth[i]) for i in keep],
        "mlr": [float(mlr_pred[i * PER_MIN] - mlr_pred[0] - truth[i]) for i in keep],
    }
    covered: dict[str, list[bool]] = {}
    usable: dict[str, list[bool]] = {}
    for m, duty_rows in served.items():
        rows = [duty_rows.minutes[i] for i in keep]
        err[m] = [r.um - r.truth_um if r.served else math.nan for r in rows]
        covered[m] = [bool(r.lo <= r.truth_um <= r.hi) for r in rows if r.served]
        usable[m] = [r.usable for r in rows]
    probe = served["probe"]
    return {
        "seed": seed,
        "mechanics": [round(v, 3) for v in (mech.restraint, mech.alpha_shaft, mech.alpha_housing)],
        "fitted": [round(float(v), 3) for v in rep.fit.x[:3]],
        "explained": bool(rep.explained),
        "mlr_sensors": list(peer.sensors),
        "mlr_fit_rms_um": round(peer.residual_rms_um, 3),
        "minutes": len(keep),
        "restart_min": restart_k // PER_MIN,
        "probe_readings": probe.readings,
        "probe_accepted": probe.accepted,
        "probe_fitted": [round(float(v), 3) for v in probe.mechanics_x],
        "not_usable": {m: _reasons(served[m].minutes, keep) for m in PRODUCT},
        "err": err,
        "covered": covered,
        "usable": usable,
        "fit_s": prep.fit_s,
        "mlr_fit_s": prep.mlr_s,
    }


@dataclass(frozen=True, kw_only=True)
class ProbePlan:
    """A probe reading (the true growth + N(0, ``sd_um``²)) every ``every_min`` after ``after_min``."""

    every_min: float
    after_min: float
    sd_um: float
    rng: np.random.Generator


@dataclass(kw_only=True)
class DutyRows:
    """A served duty cycle: a :class:`~benchmarks.compensation_run.Minute` per plant minute, the probe
    readings taken and absorbed, and the mechanics in use at the end (restraint, α shaft, α housing)."""

    minutes: list[Any]
    readings: int = 0
    accepted: int = 0
    mechanics_x: tuple[float, ...] = ()


def serve_duty(
    model: Any,
    settings: Any,
    samples: list[Any],
    run: Any,
    truth: np.ndarray,
    *,
    restart_k: int,
    mechanics: Any = None,
    probe: ProbePlan | None = None,
) -> DutyRows:
    """The duty cycle through the service as ``chtc run`` serves it (``compensation_run.Session``: shell,
    core, identification inline, growth server, the settings' policy), read every minute as
    ``/compensation`` serves it. ``mechanics``: the commissioning, set before the first sample (as a
    stored calibration is restored). The service restarts before sample ``restart_k`` with what the
    database holds then (``compensation_run.stored_state``: identification, calibration, map, zero, live
    checkpoint; the commissioning and the accepted probe readings, which are replayed). With ``probe``,
    each minute's row is read before that minute's reading is posted (``add_measurement``)."""
    from dataclasses import replace

    from benchmarks.compensation_run import PER_MIN, Session, stored_state

    session = Session(model, settings, start=samples[0].t)
    if mechanics is not None:
        session.svc.set_mechanics(mechanics)
    out = DutyRows(minutes=[])
    every_k = round(probe.every_min * PER_MIN) if probe is not None else 0
    for k, sample in enumerate(samples):
        if k == restart_k:
            svc = session.svc
            held = stored_state(svc.view, svc.growth.reference, session.stored.checkpoint())
            probes = tuple(m for m in reversed(svc.compensation_measurements()) if m.accepted)
            restored = replace(held, mechanics=mechanics, probes=probes)
            session = Session(model, settings, start=sample.t, restored=restored)
        session.clock.at_least(sample.t)
        session.svc.on_sample(sample)
        if k % PER_MIN:
            continue
        truth_um = float(truth[k // PER_MIN])
        out.minutes.append(session.read(float(run.times_s[k]), truth_um, np.asarray(run.h_true[k])))
        since = k - round(probe.after_min * PER_MIN) if probe is not None else 0
        if probe is not None and since > 0 and since % every_k == 0:
            reading = truth_um + float(probe.rng.normal(0.0, probe.sd_um))
            try:
                m = session.svc.add_measurement(
                    at=sample.t, axial_um=reading, sd_um=probe.sd_um, set_by="bench", source="probe"
                )
            except ProbeError:
                continue  # no zero or no live field yet: the shop's reading is refused, not absorbed
            out.readings += 1
            out.accepted += int(m.accepted)
    cal = session.svc.compensation_mechanics()
    out.mechanics_x = tuple(float(v) for v in cal.x[:3]) if cal is not None else ()
    return out


def _reasons(minutes: list[Any], keep: list[int]) -> dict[str, int]:
    """Minutes not usable, by the policy's typed reason."""
    out: dict[str, int] = {}
    for i in keep:
        r = minutes[i]
        if not r.usable:
            out[str(r.reason)] = out.get(str(r.reason), 0) + 1
    return out


def _r(x: Any, nd: int = 3) -> float | None:
    return None if x is None or not np.isfinite(x) else round(float(x), nd)


def method_figures(err: list[float], rms_none: float | None = None) -> dict[str, Any]:
    """|error| median, p95, max, RMS [µm] over the minutes with a value (NaN: nothing served) and the share
    of the uncompensated RMS removed."""
    e = np.abs(np.asarray(err, dtype=float))
    e = e[np.isfinite(e)]
    if e.size == 0:
        keys = ("err_um_median", "err_um_p95", "err_um_max", "rms_um", "removed")
        return dict.fromkeys(keys)
    rms = float(np.sqrt(np.mean(e**2)))
    return {
        "err_um_median": _r(np.median(e)),
        "err_um_p95": _r(np.percentile(e, 95)),
        "err_um_max": _r(e.max()),
        "rms_um": _r(rms),
        "removed": _r(1.0 - rms / rms_none) if rms_none else None,
    }


def rms_ratio(cal: list[float], mlr: list[float]) -> float | None:
    """The calibrated product's RMS over the MLR's, both over the minutes the product served a value."""
    c, m = np.asarray(cal, dtype=float), np.asarray(mlr, dtype=float)
    ok = np.isfinite(c) & np.isfinite(m)
    if not ok.any():
        return None
    den = float(np.sqrt(np.mean(m[ok] ** 2)))
    return _r(float(np.sqrt(np.mean(c[ok] ** 2))) / den) if den > 0.0 else None


PER_SEED = (
    "seed",
    "mechanics",
    "fitted",
    "explained",
    "probe_fitted",
    "probe_readings",
    "probe_accepted",
    "mlr_sensors",
    "mlr_fit_rms_um",
    "minutes",
    "restart_min",
    "not_usable",
)


def summarize(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """The pooled figures (JSON object) from ``run_seed``'s rows."""
    pooled = {m: [e for r in rows for e in r["err"][m]] for m in METHODS}
    none = method_figures(pooled["none"])
    out: dict[str, Any] = {"seeds": [r["seed"] for r in rows], "none": none}
    for m in METHODS[1:]:
        out[m] = method_figures(pooled[m], none["rms_um"])
    for m in PRODUCT:
        cov = [c for r in rows for c in r["covered"][m]]
        use = [u for r in rows for u in r["usable"][m]]
        out[m]["coverage"] = _r(np.mean(cov)) if cov else None
        out[m]["usable_fraction"] = _r(np.mean(use)) if use else None
        used = [e for r in rows for e, u in zip(r["err"][m], r["usable"][m], strict=True) if u]
        out[m]["err_um_p95_usable"] = method_figures(used)["err_um_p95"]
    out["rms_ratio_calibrated_over_mlr"] = [rms_ratio(r["err"]["calibrated"], r["err"]["mlr"]) for r in rows]
    ratios = [x for x in out["rms_ratio_calibrated_over_mlr"] if x is not None]
    out["seeds_ratio_at_most_half"] = sum(x <= 0.5 for x in ratios)
    p95, p95_probe = out["calibrated"]["err_um_p95"], out["probe"]["err_um_p95"]
    out["probe"]["p95_reduction"] = _r(1.0 - p95_probe / p95) if p95 and p95_probe is not None else None
    out["fit_wall_s"] = {
        "product": [_r(r["fit_s"], 2) for r in rows],
        "mlr": [_r(r["mlr_fit_s"], 4) for r in rows],
    }
    out["per_seed"] = [{k: r[k] for k in PER_SEED if k in r} for r in rows]
    return out


def _setup() -> tuple[Any, Any, Any]:
    """The served model, the bench's settings and the plant."""
    from benchmarks.compensation_run import Plant
    from service.commands._common import override
    from service.modelload import ModelRef, load_model
    from service.settings import Settings

    # the controller zeroed cold, as a commissioning takes the zero (the first rest in equilibrium); the
    # product's own rule for uncommissioned mechanics stays on
    settings = override(Settings(), "compensation", reference_on_first_start=True)
    model = load_model(ModelRef.from_settings(settings))
    return model, settings, Plant(model.spec)


def _seed_job(seed: int, args: argparse.Namespace) -> dict[str, Any]:
    """One seed in a worker process (``--jobs``): its own model, plant and service."""
    model, settings, plant = _setup()
    return run_seed(model, settings, plant, seed, args)


def main(args: argparse.Namespace) -> int:
    """Run the seeds, print the figures (one JSON object with ``--json``)."""
    if not 4 <= args.sensors <= 6:
        raise ValueError(f"--sensors: must be 4-6, got {args.sensors}")
    if not 0 < args.rest_min < 60.0 * args.hours:
        raise ValueError(f"--rest-min: must be in (0, {60.0 * args.hours}), got {args.rest_min}")
    if args.seeds < 1 or args.jobs < 1:
        raise ValueError(f"--seeds, --jobs: must be >= 1, got {args.seeds}, {args.jobs}")
    seeds = list(range(args.first_seed, args.first_seed + args.seeds))
    started = time.perf_counter()
    rows: dict[int, dict[str, Any]] = {}

    def done(seed: int, row: dict[str, Any]) -> None:
        rows[seed] = row
        print(f"seed {seed} done ({time.perf_counter() - started:.0f} s)", file=sys.stderr, flush=True)

    if args.jobs > 1 and len(seeds) > 1:
        from concurrent.futures import ProcessPoolExecutor, as_completed

        with ProcessPoolExecutor(max_workers=min(args.jobs, len(seeds))) as pool:
            # the options without the CLI's dispatch entries (a module does not pickle)
            opts = argparse.Namespace(**{k: v for k, v in vars(args).items() if not k.startswith("_")})
            futures = {pool.submit(_seed_job, seed, opts): seed for seed in seeds}
            for fut in as_completed(futures):
                done(futures[fut], fut.result())
    else:
        model, settings, plant = _setup()
        for seed in seeds:
            done(seed, run_seed(model, settings, plant, seed, args))
    out = summarize([rows[s] for s in seeds])
    out["wall_s"] = round(time.perf_counter() - started, 1)
    if args.json:
        print(json.dumps(out))
        return 0
    for m in METHODS:
        f = out[m]
        print(
            f"{m:>13}: |err| median {f['err_um_median']} p95 {f['err_um_p95']} max {f['err_um_max']} "
            f"RMS {f['rms_um']} µm, removed {f.get('removed')}"
            + (f", coverage {f['coverage']}, usable {f['usable_fraction']}" if "coverage" in f else "")
        )
    print(
        f"RMS calibrated / MLR per seed: {out['rms_ratio_calibrated_over_mlr']} "
        f"(<= 0.5 in {out['seeds_ratio_at_most_half']}); probe p95 reduction {out['probe']['p95_reduction']}"
    )
    print(f"fit wall [s]: {out['fit_wall_s']}")
    return 0
