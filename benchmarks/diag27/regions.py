# ruff: noqa
"""Diagnostic: where the live field's growth error sits (by region of the service mesh)."""

import sys
import numpy as np

from benchmarks.diag27.decomp import OUT
from benchmarks.commission import _setup

model, settings, plant = _setup()
fe = model.fe
names = [g.name for g in model.spec.regions]
node_reg = np.full(fe.n_nodes, -1)
for e, tri in enumerate(fe.triangles):
    for n in tri:
        if node_reg[n] < 0:
            node_reg[n] = fe.element_region[e]
phi = model.rom.basis
for seed in [int(s) for s in sys.argv[1:]]:
    z = np.load(f"{OUT}/seed{seed}.npz")
    keep = z["keep"]
    g = z["g_fit"]
    Ts = z["T_s"].astype(float)
    for arm in ("a", "d"):
        if z[f"{arm}_mean"].ndim < 2 or z[f"{arm}_mean"].shape[0] < 2:
            continue
        F = z[f"{arm}_mean"] @ phi.T  # (m, N)
        dT = (F - Ts)[keep]
        tot = dT @ g
        parts = {}
        for r, nm in enumerate(names):
            m = node_reg == r
            c = dT[:, m] @ g[m]
            if np.sqrt(np.mean(c**2)) > 0.02:
                parts[nm] = (round(float(np.mean(c)), 2), round(float(np.sqrt(np.mean(c**2))), 2))
        zero = g.sum() * (z["t_ref_true"] - z[f"{arm}_tref"][keep])
        print(
            seed,
            arm,
            "field err rms",
            round(float(np.sqrt(np.mean(tot**2))), 2),
            "mean",
            round(float(tot.mean()), 2),
            "zero",
            round(float(zero.mean()), 3),
            parts,
        )
