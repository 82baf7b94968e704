# ruff: noqa
import json, sys
import numpy as np

from benchmarks.diag27.decomp import OUT

rows = [json.loads(l) for f in sys.argv[1:] for l in open(f)]
keys = ["a", "az", "ac", "b", "b2", "c", "d", "dz", "dc", "e"]
print("seed | " + " | ".join(keys) + " | a/e | fitted | true mech")
for r in rows:
    print(
        r["seed"],
        "|",
        " | ".join(f"{r['rms'][k]:.2f} ({r['mean'][k]:+.2f})" for k in keys if k in r["rms"]),
        "|",
        round(r["rms"]["a"] / r["rms"]["e"], 2),
        r["fitted"],
        r["mech"],
    )
# pooled
import glob

pool = {k: [] for k in keys}
for r in rows:
    s = r["seed"]
    z = np.load(f"{OUT}/seed{s}.npz")
    for k in keys:
        if f"err_{k}" in z:
            pool[k].append(z[f"err_{k}"])
print(
    "pooled", " | ".join(f"{k} {np.sqrt(np.mean(np.concatenate(v) ** 2)):.3f}" for k, v in pool.items() if v)
)
