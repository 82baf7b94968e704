# ruff: noqa
"""Per-seed ratios to the MLR over 100-119 for the arms of decomp/floor/harms (from benchmarks/diag27/out)."""

import numpy as np

from benchmarks.diag27.decomp import OUT

arms = ["err_a_fit", "err_a_tf", "err_d_fit", "err_d_trueH", "err_d_tf"]
R = {k: [] for k in arms}
E = []
rows = []
for s in range(100, 120):
    z = np.load(f"{OUT}/harms{s}.npz")
    e = np.sqrt(np.mean(z["err_e"] ** 2))
    E.append(z["err_e"])
    row = [s, round(float(e), 2)]
    for k in arms:
        R[k].append(z[k])
        row.append(round(float(np.sqrt(np.mean(z[k] ** 2)) / e), 2))
    rows.append(row)
print("seed mlr " + " ".join(a[4:] for a in arms))
for r in rows:
    print(*r)
for k in arms:
    r = np.array([np.sqrt(np.mean(v**2)) for v in R[k]]) / np.array([np.sqrt(np.mean(v**2)) for v in E])
    print(
        f"{k[4:]}: pooled {np.sqrt(np.mean(np.concatenate(R[k]) ** 2)):.3f}, ratio median {np.median(r):.2f}, <=0.5 in {(r <= 0.5).sum()}/20"
    )
print(f"mlr pooled {np.sqrt(np.mean(np.concatenate(E) ** 2)):.3f}")
