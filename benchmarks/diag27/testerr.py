# ruff: noqa
import sys
import numpy as np

from benchmarks.diag27.decomp import OUT
from benchmarks.commission import _setup
from service.estimate.mechanics import served_mechanics_basis

model, settings, plant = _setup()
basis = served_mechanics_basis(model.spec, model.fe)
phi = model.rom.basis
for s in [int(x) for x in sys.argv[1:]]:
    z = np.load(f"{OUT}/test{s}.npz")
    g = basis.operators_at(z["x_true"][:3])[0]
    gp = g @ phi
    lt, ls = z["live_t"], z["live_states"]
    tt, ts = z["true_t"], z["true_states"]
    conv = z["live_conv"]
    idx = np.searchsorted(lt, tt)
    ok = idx < lt.size
    idx = np.clip(idx, 0, lt.size - 1)
    ok &= np.abs(lt[idx] - tt) < 6
    ok &= conv[idx]
    e = (ls[idx] - ts) @ gp
    e[~ok] = np.nan
    e -= np.nanmean(e[(tt - tt[0]) < 900][ok[(tt - tt[0]) < 900]]) if np.any(ok[(tt - tt[0]) < 900]) else 0
    mins = (tt - tt[0]) / 60
    line = []
    for m0 in range(0, int(mins[-1]) + 1, 10):
        sel = (mins >= m0) & (mins < m0 + 10) & ok
        line.append(f"{m0}:{np.nanmean(e[sel]):+.2f}" if sel.any() else f"{m0}:nan")
    print(s, "x_live", np.round(z["x_live"][:3], 3), "x_true", np.round(z["x_true"][:3], 3))
    print("  live-true growth (10-min means):", " ".join(line))
