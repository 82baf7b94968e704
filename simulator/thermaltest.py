"""A thermal test (ISO 230-3 style) recorded on the virtual plant: the three files ``chtc commission growth``
reads, and the truth behind them.

The plant draws (or is given) its own mechanics (``model.plantmech``); its true nose growth comes from them
on its own mesh. The files are what a real test leaves: the DAQ's temperature CSV (``drivers.logs``), the
CAN log of ``SpindleStatus`` frames (every 0.5 s), and the displacement CSV (``time,axial_um,radial_um``,
UTC) of a capacitive sensor zeroed at the start, with its noise, a fixture offset, a slow drift and a few
missing readings.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

import numpy as np

from model.plant import Segment, VirtualPlant
from model.plantmech import PlantMechanics
from service.contracts.errors import CommissioningError

__all__ = [
    "RECOMMENDED_PROFILE",
    "SHORT_PROFILE",
    "ThermalTest",
    "commission_seeds",
    "duty_check",
    "write_thermal_test",
]

# heat-up in two speed steps, then a cool-down at rest (docs/commissioning.md, "The test profile")
RECOMMENDED_PROFILE: tuple[Segment, ...] = (
    Segment(duration_s=900.0, speed_rpm=0.0, torque_nm=0.0, ambient_c=21.0),
    Segment(duration_s=3600.0, speed_rpm=4000.0, torque_nm=5.0, ambient_c=21.0),
    Segment(duration_s=3600.0, speed_rpm=7000.0, torque_nm=5.0, ambient_c=21.0),
    Segment(duration_s=6300.0, speed_rpm=0.0, torque_nm=0.0, ambient_c=21.0),
)
CAN_PERIOD_S = 0.5


@dataclass(frozen=True)
class ThermalTest:
    """The files written and the truth: the plant's ``mechanics``, the true axial and radial growth [µm]
    at ``disp_t_s`` (epoch s) over the start, and the nuisances added."""

    temperatures: Path
    canlog: Path
    displacements: Path
    mechanics: PlantMechanics
    disp_t_s: np.ndarray
    axial_true_um: np.ndarray
    radial_true_um: np.ndarray
    offset_um: float
    drift_um_per_h: float

    def commission(self, model: Any, config: Any, *, basis: Any, set_by: str = "bench") -> Any:
        """The product's commissioning of these files (``service.shell.commissioning.commission_growth``,
        the service's own core under ``config``; ``basis`` the served mechanics basis, built once)."""
        from service.shell.commissioning import commission_growth

        return commission_growth(
            model,
            config,
            self.temperatures,
            self.canlog,
            self.displacements,
            set_by=set_by,
            source="cli",
            basis=basis,
        )


def write_thermal_test(
    out: Path,
    *,
    mechanics: PlantMechanics,
    profile: Sequence[Segment] = RECOMMENDED_PROFILE,
    seed: int = 0,
    start: datetime = datetime(2026, 11, 27, 6, 0, tzinfo=UTC),
    disp_every: int = 6,
    noise_um: float = 0.1,
    offset_um: float = 2.0,
    drift_um_per_h: float = 0.1,
    missing_every: int = 17,
    plant: VirtualPlant | None = None,
) -> ThermalTest:
    """Run ``profile`` on the plant (``mechanics``, seed ``seed``) and write ``out``/temperatures.csv,
    can.blf and displacements.csv; a displacement every ``disp_every`` samples (10 s each), every
    ``missing_every``-th one left empty."""
    import can

    from drivers.can_codec import encode_status
    from drivers.logs import TemperatureCsvWriter, write_can_log
    from model.geometry import load_spindle

    out.mkdir(parents=True, exist_ok=True)
    p = plant if plant is not None else VirtualPlant(load_spindle(), seed=seed, mechanics=mechanics)
    run = p.run(profile, keep_fields_every=disp_every, rng=np.random.default_rng([seed, 3]))
    t0 = start.timestamp()
    temps = out / "temperatures.csv"
    with TemperatureCsvWriter(temps) as w:
        for k, t in enumerate(run.times_s):
            w.write(
                datetime.fromtimestamp(t0 + float(t), tz=UTC),
                temps_c=run.temps_c[k],
                ambient_c=float(run.ambient_c[k]),
                status=run.status[k],
                counter=k,
            )
    frames = []
    n_frames = int(float(run.times_s[-1]) / CAN_PERIOD_S) + 1
    for i in range(n_frames):
        tc = i * CAN_PERIOD_S
        k = min(int(np.searchsorted(run.times_s, tc, side="right")) - 1, run.times_s.size - 1)
        data = encode_status(float(run.speed_rpm[k]), float(run.torque_nm[k]), i % 16, 0)
        frames.append(can.Message(timestamp=t0 + tc, arbitration_id=0x181, is_extended_id=False, data=data))
    canlog = out / "can.blf"
    write_can_log(canlog, frames)
    names = list(p.growth.names)
    g = p.growth_um(run.fields_c, float(run.fields_c[0].mean()))
    axial, radial = g[:, names.index("nose_axial")], g[:, names.index("nose_radial")]
    td = t0 + run.field_times_s
    rng = np.random.default_rng([seed, 5])
    hours = (td - td[0]) / 3600.0
    meas_a = axial + offset_um + drift_um_per_h * hours + rng.normal(0.0, noise_um, td.size)
    meas_r = radial + rng.normal(0.0, noise_um, td.size)
    disp = out / "displacements.csv"
    with disp.open("w", encoding="utf-8") as f:
        f.write("# ISO 230-3 style thermal test on the virtual plant (chtc commission growth)\n")
        f.write("time,axial_um,radial_um\n")
        for i, t in enumerate(td):
            stamp = datetime.fromtimestamp(float(t), tz=UTC) + timedelta(0)
            a = "" if missing_every and i % missing_every == missing_every - 1 else f"{meas_a[i]:.3f}"
            f.write(f"{stamp.isoformat().replace('+00:00', 'Z')},{a},{meas_r[i]:.3f}\n")
    return ThermalTest(
        temperatures=temps,
        canlog=canlog,
        displacements=disp,
        mechanics=mechanics,
        disp_t_s=td,
        axial_true_um=axial,
        radial_true_um=radial,
        offset_um=offset_um,
        drift_um_per_h=drift_um_per_h,
    )


SHORT_PROFILE: tuple[Segment, ...] = (  # the smallest test that pins the restraint (the shipped example)
    Segment(duration_s=600.0, speed_rpm=0.0, torque_nm=0.0, ambient_c=21.0),
    Segment(duration_s=2400.0, speed_rpm=7000.0, torque_nm=5.0, ambient_c=21.0),
    Segment(duration_s=1800.0, speed_rpm=0.0, torque_nm=0.0, ambient_c=21.0),
)


def commission_seeds(
    first: int, last: int, *, profile: Sequence[Segment] = RECOMMENDED_PROFILE
) -> list[dict[str, Any]]:
    """Seeds ``first``..``last - 1``: a thermal test on each drawn plant, commissioned with the default
    settings; per seed the truth, the fit (value, 1σ, CI covers the truth), the verdict and the cost (the
    figures of docs/design/growth.md, "Commissioning on the service's field")."""
    import tempfile
    import time

    from model.plantmech import mechanics_for_seed
    from service.estimate.mechanics import served_mechanics_basis
    from service.host.runtime import core_config
    from service.modelload import ModelRef, load_model
    from service.settings import Settings

    settings = Settings()
    model = load_model(ModelRef.from_settings(settings))
    basis = served_mechanics_basis(model.spec, model.fe)
    rows: list[dict[str, Any]] = []
    for seed in range(first, last):
        mech = mechanics_for_seed(seed)
        with tempfile.TemporaryDirectory(prefix="chtc-thermal-test-") as tmp:
            t = write_thermal_test(Path(tmp), mechanics=mech, profile=profile, seed=seed)
            started = time.perf_counter()
            try:
                rep = t.commission(model, core_config(settings), basis=basis)
            except CommissioningError as err:
                rows.append({"seed": seed, "error": str(err)})
                continue
        f = rep.fit
        truth = (mech.restraint, mech.alpha_shaft, mech.alpha_housing)
        rows.append(
            {
                "seed": seed,
                "truth": [round(v, 4) for v in truth],
                "x": [round(float(v), 4) for v in f.x[:3]],
                "sd": [round(float(v), 4) for v in f.sd[:3]],
                "covered": [bool(f.ci95[i, 0] <= truth[i] <= f.ci95[i, 1]) for i in range(3)],
                "explained": rep.explained,
                "residual_rms_um": round(f.residual_rms_um, 4),
                "residual_max_um": round(f.residual_max_um, 4),
                "outliers": rep.outliers,
                "problems": rep.problems,
                "fit_s": round(rep.timings_s["fit_s"], 4),
                "wall_s": round(time.perf_counter() - started, 1),
            }
        )
    return rows


def duty_check(seed: int, *, hours: float = 2.0, after_min: float = 30.0) -> dict[str, Any]:
    """Out of sample: commission seed ``seed``'s drawn plant on the 4-h test, then serve a duty cycle
    (``simulator.duty``, seed + 1000) on the same plant through the service's core: the axial growth with
    the calibrated operators against the plant's truth every minute after ``after_min``, its CI (the live
    state's covariance, which holds the considered H error, and the mechanical posterior) and its coverage;
    the uncalibrated (the description's mechanics) error beside it. No reference 1σ and no identification
    gating: the growth and its CI as ``estimate_growth`` forms them now."""
    import tempfile

    from model.geometry import load_spindle
    from model.plantmech import mechanics_for_seed
    from service.core.offline import run_offline
    from service.estimate.mechanics import served_mechanics_basis
    from service.host.runtime import core_config
    from service.modelload import ModelRef, load_model
    from service.settings import Settings
    from simulator.duty import duty_profile
    from simulator.plantsamples import samples_from_plant

    z95 = 1.959963984540054
    settings = Settings()
    model = load_model(ModelRef.from_settings(settings))
    config = core_config(settings)
    basis = served_mechanics_basis(model.spec, model.fe)
    phi = np.asarray(model.rom.basis)
    mech = mechanics_for_seed(seed)
    with tempfile.TemporaryDirectory(prefix="chtc-thermal-test-") as tmp:
        t = write_thermal_test(Path(tmp), mechanics=mech, seed=seed)
        rep = t.commission(model, config, basis=basis, set_by="check")
    x, cov = rep.fit.x[:3], rep.fit.cov[:3, :3]
    profile = duty_profile(seed + 1000, duration_s=3600.0 * hours, idle_s=600.0)
    t_ref = profile[0].ambient_c
    plant = VirtualPlant(load_spindle(), seed=seed + 1000, mechanics=mech)
    run = plant.run(profile, keep_fields_every=6)
    truth = plant.growth_um(run.fields_c, t_ref)[:, list(plant.growth.names).index("nose_axial")]
    t0 = 1.8e9
    states: dict[float, tuple[np.ndarray, np.ndarray]] = {}

    def keep(core: Any, k: int, last: object) -> None:
        live = core.view().live
        if live is not None and live.converged:
            states[round(float(live.t) - t0, 3)] = (np.array(live.mean), np.array(live.cov))

    run_offline(samples_from_plant(run, t0_s=t0), model=model, config=config, on_sample=keep)
    ops = {"cal": basis.operators_at(x)[0], "nominal": basis.operators_at((0.0, 1.0, 1.0))[0]}
    g = {k: v @ phi for k, v in ops.items()}
    g1 = {k: float(v.sum()) for k, v in ops.items()}
    jac = basis.jacobian_at(x)[0]
    j_phi, j1 = jac @ phi, jac.sum(axis=1)
    err: dict[str, list[float]] = {"cal": [], "nominal": []}
    covered, half = [], []
    for i, tt in enumerate(run.field_times_s):
        key = round(float(tt), 3)
        if key not in states or tt < 60.0 * after_min:
            continue
        a, p = states[key]
        for k in err:
            err[k].append(float(g[k] @ a - g1[k] * t_ref - truth[i]))
        j = j_phi @ a - j1 * t_ref
        sd = float(np.sqrt(g["cal"] @ p @ g["cal"] + j @ cov @ j))
        covered.append(abs(err["cal"][-1]) <= z95 * sd)
        half.append(z95 * sd)
    e, en = np.abs(err["cal"]), np.abs(err["nominal"])
    return {
        "seed": seed,
        "mechanics": [round(v, 3) for v in (mech.restraint, mech.alpha_shaft, mech.alpha_housing)],
        "fitted": [round(float(v), 3) for v in x],
        "explained": rep.explained,
        "minutes": int(e.size),
        "err_um_median": round(float(np.median(e)), 3),
        "err_um_p95": round(float(np.percentile(e, 95)), 3),
        "err_um_max": round(float(e.max()), 3),
        "coverage": round(float(np.mean(covered)), 3),
        "ci95_half_um_median": round(float(np.median(half)), 3),
        "uncalibrated_err_um_median": round(float(np.median(en)), 3),
        "uncalibrated_err_um_p95": round(float(np.percentile(en, 95)), 3),
        "truth_um_max": round(float(np.abs(truth).max()), 2),
    }


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m simulator.thermaltest OUT [--seed N] [--short]``: write a thermal test into OUT;
    ``--commission-seeds A B``: commission seeds A..B-1 and print one JSON line each; ``--duty-check-seeds S
    ...``: ``duty_check`` for each seed, one JSON line each."""
    import argparse
    import json

    from model.plantmech import mechanics_for_seed

    p = argparse.ArgumentParser(prog="python -m simulator.thermaltest", description=__doc__)
    p.add_argument("out", type=Path, nargs="?", default=None, help="directory for the three files")
    p.add_argument("--seed", type=int, default=3, help="the plant's seed (its drawn mechanics)")
    p.add_argument("--short", action="store_true", help="the 80-min profile instead of the 4-h one")
    p.add_argument("--commission-seeds", type=int, nargs=2, metavar=("FIRST", "END"), default=None)
    p.add_argument("--duty-check-seeds", type=int, nargs="+", metavar="SEED", default=None)
    args = p.parse_args(argv)
    if args.duty_check_seeds is not None:
        for seed in args.duty_check_seeds:
            print(json.dumps(duty_check(seed)), flush=True)
        return 0
    profile = SHORT_PROFILE if args.short else RECOMMENDED_PROFILE
    if args.commission_seeds is not None:
        for row in commission_seeds(*args.commission_seeds, profile=profile):
            print(json.dumps(row), flush=True)
        return 0
    if args.out is None:
        p.error("OUT is needed unless --commission-seeds")
    t = write_thermal_test(args.out, mechanics=mechanics_for_seed(args.seed), profile=profile, seed=args.seed)
    print(f"{t.temperatures}, {t.canlog}, {t.displacements}: plant mechanics {t.mechanics.as_dict()}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
