# ruff: noqa
"""Diagnostic: commissioning fit variants on the saved test histories ($CHTC_DIAG_OUT/test*.npz), evaluated on the
saved duty ($CHTC_DIAG_OUT/seed*.npz): a = product live field with that θ, b = true field with that θ."""

from __future__ import annotations

import sys

import numpy as np

from benchmarks.diag27.decomp import OUT


def main() -> int:
    from benchmarks.commission import _setup
    from service.shell.commissioning import Displacements, FieldHistory, fit_test
    from service.estimate.mechanics import served_mechanics_basis

    model, _, _ = _setup()
    basis = served_mechanics_basis(model.spec, model.fe)
    phi = np.asarray(model.rom.basis)
    seeds = [int(s) for s in sys.argv[1:]]
    pooled: dict[str, list[np.ndarray]] = {}
    ratios: dict[str, list[float]] = {}
    for seed in seeds:
        t = np.load(OUT / f"test{seed}.npz")
        z = np.load(OUT / f"seed{seed}.npz")
        disp = Displacements(t_s=t["disp_t"], axial_um=t["disp_ax"], radial_um=t["disp_rad"])
        lt, conv, sp = t["live_t"], t["live_conv"], t["live_speed"]
        mins = (lt - lt[0]) / 60.0
        # time since the last speed change [min]
        change = np.r_[True, np.abs(np.diff(sp)) > 1.0]
        last = np.maximum.accumulate(np.where(change, np.arange(sp.size), 0))
        since = mins - mins[last]
        variants = {
            "base": conv,
            "settled20": conv & (since >= 20.0),
            "rest_only": conv & (sp == 0.0),
            "cool_only": conv & (sp == 0.0) & (mins > 60.0),
        }
        res = {}
        for name, mask in variants.items():
            hist = FieldHistory(t_s=lt, states=t["live_states"], converged=mask, speed_rpm=sp)
            try:
                x = fit_test(basis, phi, hist, disp)[0].result.x
            except Exception as err:  # noqa: BLE001
                res[name] = f"fail {err}"
                continue
            res[name] = x
        res["true_field"] = t["x_true"]
        keep, truth = z["keep"], z["truth"]
        fields = z["a_mean"] @ phi.T
        ts = z["T_s"].astype(float)
        mlr = float(np.sqrt(np.mean(z["err_e"] ** 2)))
        line = [f"seed {seed} mlr {mlr:.2f}"]
        for name, x in res.items():
            if isinstance(x, str):
                line.append(f"{name}: {x[:60]}")
                continue
            g = basis.operators_at(x[:3])[0]
            ea = (fields @ g - g.sum() * z["a_tref"])[keep] - truth[keep]
            eb = (ts @ g - g.sum() * z["t_ref_true"])[keep] - truth[keep]
            ra, rb = np.sqrt(np.mean(ea**2)), np.sqrt(np.mean(eb**2))
            pooled.setdefault(name, []).append(ea)
            ratios.setdefault(name, []).append(ra / mlr)
            line.append(f"{name} x={np.round(x[:3], 3)} a {ra:.2f} b {rb:.2f}")
        print("\n  ".join(line), flush=True)
    for name, v in pooled.items():
        r = np.array(ratios[name])
        print(
            f"{name}: pooled a {np.sqrt(np.mean(np.concatenate(v) ** 2)):.3f}, ratio median {np.median(r):.2f},"
            f" <=0.5 in {int((r <= 0.5).sum())}/{r.size}"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
