# ruff: noqa
"""Diagnostic: the commissioning's fitted mechanics on the service's live test field vs on the plant's TRUE
test field (interpolated onto the service mesh, E-projected on the ROM basis), and what each θ gives on the
duty (from $CHTC_DIAG_OUT/seed*.npz of decomp.py). Saves the test's live and true histories for re-fits."""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import numpy as np

from benchmarks.diag27.decomp import OUT, interp_matrix


def main() -> int:
    from model.plant import VirtualPlant
    from simulator.randomtruth import draw_truth
    from benchmarks.commission import _setup
    from service.shell.commissioning import FieldHistory, field_history, fit_test, read_displacement_csv
    from service.host.runtime import core_config
    from service.estimate.mechanics import served_mechanics_basis
    from simulator.thermaltest import RECOMMENDED_PROFILE, write_thermal_test

    model, settings, plant = _setup()
    config = core_config(settings)
    basis = served_mechanics_basis(model.spec, model.fe)
    P = interp_matrix(plant.fe, model.fe)
    rom = model.rom
    phi = np.asarray(rom.basis)
    for seed in [int(s) for s in sys.argv[1:]]:
        mech = plant.mechanics(seed)
        truth_h = draw_truth(np.random.default_rng([seed, 7]))  # one machine: its test's and its duty's H
        tp = VirtualPlant(
            plant.spec, fe=plant.fe, seed=seed, mechanics=mech, growth=plant.growth(seed), h_law=truth_h
        )
        with tempfile.TemporaryDirectory(prefix="diag-") as tmp:
            t = write_thermal_test(
                Path(tmp), mechanics=mech, profile=RECOMMENDED_PROFILE, seed=seed, plant=tp
            )
            run = tp.run(RECOMMENDED_PROFILE, keep_fields_every=6, rng=np.random.default_rng([seed, 3]))
            hist = field_history(model, config, t.temperatures, t.canlog)
            disp = read_displacement_csv(t.displacements)
        t0 = float(t.disp_t_s[0])
        states_true = rom.project(np.asarray((P @ run.fields_c.T).T))
        hist_true = FieldHistory(
            t_s=t0 + run.field_times_s,
            states=states_true,
            converged=np.ones(run.field_times_s.size, dtype=bool),
            speed_rpm=run.speed_rpm[::6][: run.field_times_s.size],
        )
        fit_live = fit_test(basis, phi, hist, disp)[0].result
        fit_true = fit_test(basis, phi, hist_true, disp)[0].result
        np.savez_compressed(
            OUT / f"test{seed}.npz",
            live_t=hist.t_s,
            live_states=hist.states,
            live_conv=hist.converged,
            live_speed=hist.speed_rpm,
            true_t=hist_true.t_s,
            true_states=states_true,
            true_speed=hist_true.speed_rpm,
            disp_t=disp.t_s,
            disp_ax=disp.axial_um,
            disp_rad=disp.radial_um,
            x_live=fit_live.x,
            x_true=fit_true.x,
        )
        out = {"seed": seed, "true": [mech.restraint, mech.alpha_shaft, mech.alpha_housing]}
        out["live_fit"] = [round(float(v), 3) for v in fit_live.x]
        out["true_fit"] = [round(float(v), 3) for v in fit_true.x]
        f = OUT / f"seed{seed}.npz"
        if f.exists():
            z = np.load(f)
            keep, truth = z["keep"], z["truth"]
            fields_live = z["a_mean"] @ phi.T
            ts = z["T_s"].astype(float)
            for name, x in (("live_fit", fit_live.x), ("true_fit", fit_true.x)):
                g = basis.operators_at(x[:3])[0]
                e_a = (fields_live @ g - g.sum() * z["a_tref"])[keep] - truth[keep]
                e_b = (ts @ g - g.sum() * z["t_ref_true"])[keep] - truth[keep]
                out[f"duty_{name}"] = {
                    "a": round(float(np.sqrt(np.mean(e_a**2))), 3),
                    "b": round(float(np.sqrt(np.mean(e_b**2))), 3),
                }
            out["mlr"] = round(float(np.sqrt(np.mean(z["err_e"] ** 2))), 3)
        print(out, flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
