"""``chtc bench commission``: the product's commissioning against the literature's peer, side by side
(issue 27 item 4).

Data are SYNTHETIC. Per seed the plant draws its own mechanics (``model.plantmech``, unknown to the service)
and runs the simulated ISO 230-3 thermal test (``service.sim.thermaltest``: temperatures, CAN log,
displacements with noise, fixture offset, drift and missing readings). On that one test:

- the product commissions (``service.engine.commissioning.commission_growth``, the service's own core);
- the peer fits an MLR (``model.mlr``: 4–6 sensors by correlation clustering, least squares of the measured
  axial displacement on their temperatures plus an intercept).

Then on a separate duty cycle of the same plant (``service.sim.duty``, seed's random H(speed) truth
``service.sim.randomtruth``, per-channel offsets ±0.2 °C: ``service.bench.compensation_run.Plant``), every
minute after the rest, the axial error against the plant's true growth (over its cold uniform start):

- ``none``: no compensation (the error is the growth itself);
- ``mlr``: the MLR's prediction minus its prediction at the first sample (zeroed cold, as the controller is);
- ``uncalibrated``: the product's growth with the description's mechanics; CI from the live state only;
- ``calibrated``: with the commissioned mechanics; CI from the live state and the mechanical posterior;
- ``probe``: the calibrated, plus a probe reading (the true growth + N(0, ``--probe-sd-um``²)) every
  ``--probe-min`` after the rest absorbed into the mechanical posterior (``service.estimate.probe.absorb``);
  each minute's error is the one served before that minute's reading.

The product's growth is formed as ``service.sim.thermaltest.duty_check`` forms it (the core's converged live
state through the growth operators, no identification gating): ``usable_fraction`` here is the share of the
minutes with a converged live state, not the served policy's verdict (``chtc bench compensation`` has that).
Figures per method, pooled over the seeds: |error| median, p95, max and RMS [µm], and ``removed`` (1 − RMS /
RMS without compensation).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

Z95 = 1.959963984540054
METHODS = ("none", "mlr", "uncalibrated", "calibrated", "probe")
PRODUCT = ("calibrated", "uncalibrated", "probe")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``chtc bench commission``."""
    parser.add_argument("--seeds", type=int, default=3, help="drawn plants (default 3)")
    parser.add_argument("--first-seed", type=int, default=0, help="first seed, default 0")
    parser.add_argument("--hours", type=float, default=2.5, help="duty cycle length incl. the rest (2.5 h)")
    parser.add_argument("--rest-min", type=int, default=30, help="rest before machining, min (30)")
    parser.add_argument("--short", action="store_true", help="the 80-min thermal test instead of the 4-h one")
    parser.add_argument("--sensors", type=int, default=5, help="MLR sensors (clusters), 4-6 (default 5)")
    parser.add_argument("--probe-min", type=float, default=60.0, help="probe reading period, min (60)")
    parser.add_argument("--probe-sd-um", type=float, default=1.0, help="probe reading 1σ, µm (1)")
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
    from drivers.logs import read_temperature_csv
    from model.mlr import fit_mlr

    log = read_temperature_csv(temperatures)
    td, axial = read_axial(displacements)
    k = np.clip(np.searchsorted(log.t_s, td + 1e-6, side="right") - 1, 0, log.n_rows - 1)
    return fit_mlr(log.temps_c[k], axial, n_clusters=n_sensors)


def run_seed(model: Any, settings: Any, plant: Any, seed: int, args: argparse.Namespace) -> dict[str, Any]:
    """One seed: the thermal test, both fits, the duty cycle; per-minute errors per method (module
    docstring)."""
    from model.plant import VirtualPlant
    from service.bench.compensation_run import PER_MIN, T0
    from service.engine.offline import run_offline
    from service.engine.runtime import core_config
    from service.estimate.mechanics import served_mechanics_basis
    from service.estimate.probe import absorb
    from service.sim.duty import duty_profile
    from service.sim.logsamples import samples_from_plant
    from service.sim.randomtruth import draw_truth
    from service.sim.thermaltest import RECOMMENDED_PROFILE, SHORT_PROFILE, write_thermal_test

    config = core_config(settings)
    basis = served_mechanics_basis(model.spec, model.fe)
    mech = plant.mechanics(seed)
    test_plant = VirtualPlant(plant.spec, fe=plant.fe, seed=seed, mechanics=mech, growth=plant.growth(seed))
    with tempfile.TemporaryDirectory(prefix="chtc-bench-commission-") as tmp:
        profile = SHORT_PROFILE if args.short else RECOMMENDED_PROFILE
        t = write_thermal_test(Path(tmp), mechanics=mech, profile=profile, seed=seed, plant=test_plant)
        started = time.perf_counter()
        rep = t.commission(model, config, basis=basis)
        fit_s = time.perf_counter() - started
        started = time.perf_counter()
        peer = fit_peer(t.temperatures, t.displacements, n_sensors=args.sensors)
        mlr_s = time.perf_counter() - started
    x, cov = rep.fit.x[:3], rep.fit.cov[:3, :3]

    total_min = round(60.0 * args.hours)
    truth_h = draw_truth(np.random.default_rng([seed, 7]))
    duty = duty_profile(seed, duration_s=60.0 * total_min, idle_s=60.0 * args.rest_min)
    run, truth = plant.run(seed, "offsets", duty, truth_h)
    t_ref = plant.start_c(run)
    states: dict[float, tuple[np.ndarray, np.ndarray]] = {}

    def keep(core: Any, k: int, last: object) -> None:
        live = core.view().live
        if live is not None and live.converged:
            states[round(float(live.t) - T0, 3)] = (np.array(live.mean), np.array(live.cov))

    run_offline(samples_from_plant(run, t0_s=T0), model=model, config=config, on_sample=keep)
    phi = np.asarray(model.rom.basis)
    ops = {"calibrated": basis.operators_at(x)[0], "uncalibrated": basis.operators_at((0.0, 1.0, 1.0))[0]}
    g = {k: v @ phi for k, v in ops.items()}
    g1 = {k: float(v.sum()) for k, v in ops.items()}
    jac = basis.jacobian_at(x)[0]
    j_phi, j1 = jac @ phi, jac.sum(axis=1)
    op_ax = basis.operators[0]  # (2 mounts, 3 α groups, N)
    f_phi, f1 = np.einsum("mjn,nr->mjr", op_ax, phi), op_ax.sum(axis=2)
    xp, covp = np.array(x, dtype=float), np.array(cov, dtype=float)
    probe_every = round(args.probe_min * 60.0)
    mlr_pred = peer.predict(run.temps_c)
    rng = np.random.default_rng([seed, 11])
    err: dict[str, list[float]] = {m: [] for m in METHODS}
    covered: dict[str, list[bool]] = {m: [] for m in PRODUCT}
    readings = accepted = 0
    minutes = 0
    for i, tt in enumerate(run.field_times_s):
        if tt < 60.0 * args.rest_min:
            continue
        minutes += 1
        err["none"].append(float(-truth[i]))
        err["mlr"].append(float(mlr_pred[i * PER_MIN] - mlr_pred[0] - truth[i]))
        key = round(float(tt), 3)
        if key not in states:
            continue
        a, p = states[key]
        for m in ("calibrated", "uncalibrated"):
            err[m].append(float(g[m] @ a - g1[m] * t_ref - truth[i]))
        j = j_phi @ a - j1 * t_ref
        field_var = float(g["calibrated"] @ p @ g["calibrated"])
        sd_cal = float(np.sqrt(field_var + j @ cov @ j))
        sd_nom = float(np.sqrt(g["uncalibrated"] @ p @ g["uncalibrated"]))
        covered["calibrated"].append(abs(err["calibrated"][-1]) <= Z95 * sd_cal)
        covered["uncalibrated"].append(abs(err["uncalibrated"][-1]) <= Z95 * sd_nom)
        gp = basis.operators_at(xp)[0] @ phi
        jp = basis.jacobian_at(xp)[0]
        jpa = jp @ phi @ a - jp.sum(axis=1) * t_ref
        var_p = float(gp @ p @ gp)
        err["probe"].append(float(gp @ a - float(basis.operators_at(xp)[0].sum()) * t_ref - truth[i]))
        covered["probe"].append(abs(err["probe"][-1]) <= Z95 * float(np.sqrt(var_p + jpa @ covp @ jpa)))
        since = round(float(tt)) - 60 * args.rest_min
        if since > 0 and probe_every > 0 and since % probe_every == 0:
            reading = float(truth[i]) + float(rng.normal(0.0, args.probe_sd_um))
            up = absorb(xp, covp, f_phi @ a - f1 * t_ref, reading, args.probe_sd_um**2 + var_p)
            xp, covp = up.x, up.cov
            readings += 1
            accepted += int(up.accepted)
    return {
        "seed": seed,
        "mechanics": [round(v, 3) for v in (mech.restraint, mech.alpha_shaft, mech.alpha_housing)],
        "fitted": [round(float(v), 3) for v in x],
        "mlr_sensors": list(peer.sensors),
        "mlr_fit_rms_um": round(peer.residual_rms_um, 3),
        "minutes": minutes,
        "probe_readings": readings,
        "probe_accepted": accepted,
        "probe_fitted": [round(float(v), 3) for v in xp],
        "err": err,
        "covered": covered,
        "fit_s": fit_s,
        "mlr_fit_s": mlr_s,
    }


def _r(x: Any, nd: int = 3) -> float | None:
    return None if x is None or not np.isfinite(x) else round(float(x), nd)


def method_figures(err: list[float], rms_none: float | None = None) -> dict[str, Any]:
    """|error| median, p95, max, RMS [µm] and the share of the uncompensated RMS removed."""
    e = np.abs(np.asarray(err, dtype=float))
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


def summarize(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """The pooled figures (JSON object) from ``run_seed``'s rows."""
    pooled = {m: [e for r in rows for e in r["err"][m]] for m in METHODS}
    none = method_figures(pooled["none"])
    out: dict[str, Any] = {"seeds": [r["seed"] for r in rows], "none": none}
    minutes = sum(r["minutes"] for r in rows)
    for m in METHODS[1:]:
        out[m] = method_figures(pooled[m], none["rms_um"])
    for m in PRODUCT:
        cov = [c for r in rows for c in r["covered"][m]]
        out[m]["coverage"] = _r(np.mean(cov)) if cov else None
        out[m]["usable_fraction"] = _r(len(cov) / minutes) if minutes else None
    ratio = []
    for r in rows:
        cal, mlr = method_figures(r["err"]["calibrated"]), method_figures(r["err"]["mlr"])
        ok = cal["rms_um"] is not None and mlr["rms_um"]
        ratio.append(_r(cal["rms_um"] / mlr["rms_um"]) if ok else None)
    out["rms_ratio_calibrated_over_mlr"] = ratio
    out["fit_wall_s"] = {
        "product": [_r(r["fit_s"], 2) for r in rows],
        "mlr": [_r(r["mlr_fit_s"], 4) for r in rows],
    }
    out["per_seed"] = [
        {
            k: r[k]
            for k in (
                "seed",
                "mechanics",
                "fitted",
                "probe_fitted",
                "probe_readings",
                "probe_accepted",
                "mlr_sensors",
                "mlr_fit_rms_um",
                "minutes",
            )
        }
        for r in rows
    ]
    return out


def main(args: argparse.Namespace) -> int:
    """Run the seeds, print the figures (one JSON object with ``--json``)."""
    from service.bench.compensation_run import Plant
    from service.modelload import ModelRef, load_model
    from service.settings import Settings

    if not 4 <= args.sensors <= 6:
        raise ValueError(f"--sensors: must be 4-6, got {args.sensors}")
    if not 0 < args.rest_min < 60.0 * args.hours:
        raise ValueError(f"--rest-min: must be in (0, {60.0 * args.hours}), got {args.rest_min}")
    settings = Settings()
    model = load_model(ModelRef.from_settings(settings))
    plant = Plant(model.spec)
    rows = []
    for seed in range(args.first_seed, args.first_seed + args.seeds):
        started = time.perf_counter()
        rows.append(run_seed(model, settings, plant, seed, args))
        print(f"seed {seed}: {time.perf_counter() - started:.0f} s", file=sys.stderr, flush=True)
    out = summarize(rows)
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
    print(f"RMS calibrated / MLR per seed: {out['rms_ratio_calibrated_over_mlr']}")
    print(f"fit wall [s]: {out['fit_wall_s']}")
    return 0
