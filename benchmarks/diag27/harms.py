# ruff: noqa
"""Diagnostic: (1) the commissioning on a live test field run with the test plant's TRUE H (the seed's drawn truth);
(2) the duty served with the H of the duty's FINAL speed map (hindsight: is the map learnt too slowly?).
Needs $CHTC_DIAG_OUT/seed*.npz (decomp.py) and test*.npz (commfit.py)."""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import numpy as np

from benchmarks.diag27.decomp import OUT, fixed_h


def main() -> int:
    from model.plant import VirtualPlant
    from benchmarks.commission import _setup
    from benchmarks.compensation_run import PER_MIN, T0, Session, stored_state
    from service.shell.commissioning import field_history, fit_test, read_displacement_csv
    from service.host.runtime import core_config
    from service.estimate.mechanics import served_mechanics_basis
    from simulator.duty import duty_profile
    from simulator.plantsamples import samples_from_plant
    from simulator.randomtruth import draw_truth
    from simulator.thermaltest import RECOMMENDED_PROFILE, write_thermal_test

    model, settings, plant = _setup()
    config = core_config(settings)
    basis = served_mechanics_basis(model.spec, model.fe)
    phi = np.asarray(model.rom.basis)
    for seed in [int(s) for s in sys.argv[1:] if not s.startswith("--")]:
        z = np.load(OUT / f"seed{seed}.npz")
        tz = np.load(OUT / f"test{seed}.npz")
        mech = plant.mechanics(seed)
        truth_h = draw_truth(np.random.default_rng([seed, 7]))  # one machine: its test's and its duty's H
        tp = VirtualPlant(
            plant.spec, fe=plant.fe, seed=seed, mechanics=mech, growth=plant.growth(seed), h_law=truth_h
        )
        with tempfile.TemporaryDirectory(prefix="diag-") as tmp:
            t = write_thermal_test(
                Path(tmp), mechanics=mech, profile=RECOMMENDED_PROFILE, seed=seed, plant=tp
            )
            with fixed_h(lambda n, _amb: truth_h(n)):
                hist = field_history(model, config, t.temperatures, t.canlog)
            disp = read_displacement_csv(t.displacements)
        x_th = fit_test(basis, phi, hist, disp)[0].result.x
        # the duty again (the a arm) to get its final map, then served with that map's H
        duty = duty_profile(seed, duration_s=60.0 * 150, idle_s=60.0 * 30)
        run, truth = plant.run(seed, "offsets", duty, truth_h)
        samples = samples_from_plant(run, t0_s=T0)
        restart_k = PER_MIN * (30 + 120 // 2)
        from service.contracts.mechanics import MechanicsCalibration

        cal = None

        def serve(law=None):
            nonlocal cal
            from datetime import UTC, datetime

            x = tuple(float(v) for v in z["fitted"])
            cal = MechanicsCalibration(
                x=x,
                cov=tuple(tuple(0.0 for _ in range(3)) for _ in range(3)),
                at=datetime(2026, 1, 1, tzinfo=UTC),
                set_by="diag",
                source="cli",
            )
            means, trefs = [], []
            session = Session(model, settings, start=samples[0].t)
            session.svc.set_mechanics(cal)
            from dataclasses import replace

            for k, sample in enumerate(samples):
                if k == restart_k:
                    svc = session.svc
                    held = stored_state(svc.view, svc.growth.reference, session.stored.checkpoint())
                    session = Session(model, settings, start=sample.t, restored=replace(held, mechanics=cal))
                session.clock.at_least(sample.t)
                session.svc.on_sample(sample)
                if k % PER_MIN:
                    continue
                live = session.svc.view.live
                means.append(np.full(phi.shape[1], np.nan) if live is None else np.asarray(live.mean))
                tr = session.svc.growth.t_ref_c(session.svc.view)
                trefs.append(np.nan if tr is None else tr)
            return np.array(means), np.array(trefs), session.svc.view.speed_map

        f_mean = f_tref = np.full((1, 1), np.nan)
        if "--no-f" not in sys.argv:
            _, _, final_map = serve()
            fam_h = lambda n, amb: final_map.h_at([abs(n)], amb)[0][0]  # noqa: E731
            with fixed_h(fam_h):
                f_mean, f_tref, _ = serve()
        keep, tr = z["keep"], z["truth"][z["keep"]]
        mlr = float(np.sqrt(np.mean(z["err_e"] ** 2)))
        out = [
            f"seed {seed} mlr {mlr:.2f} x_fit {np.round(z['fitted'], 3)} x_trueH {np.round(x_th[:3], 3)} "
            f"x_truefield {np.round(tz['x_true'][:3], 3)}"
        ]
        arms = {"a": (z["a_mean"], z["a_tref"]), "d": (z["d_mean"], z["d_tref"]), "f": (f_mean, f_tref)}
        errs = {}
        for arm, (mean, tref) in arms.items():
            if mean.ndim < 2 or mean.shape[0] < 2:
                continue
            F = mean @ phi.T
            for nm, x in (("fit", z["fitted"]), ("trueH", x_th), ("tf", tz["x_true"])):
                g = basis.operators_at(x[:3])[0]
                e = (F @ g - g.sum() * tref)[keep] - tr
                errs[f"{arm}_{nm}"] = e
        out.append(
            " ".join(
                f"{k} {np.sqrt(np.mean(e**2)):.2f} ({np.sqrt(np.mean(e**2)) / mlr:.2f})"
                for k, e in errs.items()
            )
        )
        np.savez_compressed(
            OUT / f"harms{seed}.npz",
            x_trueH=x_th,
            f_mean=f_mean,
            f_tref=f_tref,
            **{f"err_{k}": v for k, v in errs.items()},
            err_e=z["err_e"],
        )
        print("\n  ".join(out), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
