# ruff: noqa
import sys
import numpy as np

from benchmarks.diag27.decomp import OUT
from benchmarks.commission import _setup
from service.estimate.mechanics import served_mechanics_basis

model, _, _ = _setup()
basis = served_mechanics_basis(model.spec, model.fe)
phi = model.rom.basis
R = {"a_fit": [], "a_tf": [], "d_fit": [], "d_tf": [], "e": []}
for s in [int(x) for x in sys.argv[1:]]:
    z = np.load(f"{OUT}/seed{s}.npz")
    t = np.load(f"{OUT}/test{s}.npz")
    keep, tr = z["keep"], z["truth"][z["keep"]]
    row = {}
    for arm in ("a", "d"):
        F = z[f"{arm}_mean"] @ phi.T
        for nm, x in (("fit", z["fitted"]), ("tf", t["x_true"])):
            g = basis.operators_at(x[:3])[0]
            e = (F @ g - g.sum() * z[f"{arm}_tref"])[keep] - tr
            R[f"{arm}_{nm}"].append(e)
            row[f"{arm}_{nm}"] = np.sqrt(np.mean(e**2))
    R["e"].append(z["err_e"])
    m = np.sqrt(np.mean(z["err_e"] ** 2))
    print(
        s,
        " ".join(f"{k} {v:.2f} ({v / m:.2f}) mean {np.mean(R[k][-1]):+.2f}" for k, v in row.items()),
        f"mlr {m:.2f}",
    )
print("pooled", " ".join(f"{k} {np.sqrt(np.mean(np.concatenate(v) ** 2)):.3f}" for k, v in R.items()))
