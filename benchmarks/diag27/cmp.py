# ruff: noqa
import json, sys
import numpy as np

from benchmarks.diag27.decomp import OUT


def load(f):
    return {json.loads(l)["seed"]: json.loads(l) for l in open(f)}


base = load(sys.argv[1])
for f in sys.argv[2:]:
    v = load(f)
    seeds = sorted(set(base) & set(v))

    def pooled(tag, d):
        es = [np.load(f"{OUT}/seed{s}{tag}.npz")["err_a"] for s in seeds]
        return np.sqrt(np.mean(np.concatenate(es) ** 2))

    tag = f.split("var")[-1].split("_0_9")[0].split("_100")[0] if "var" in f else ""
    rb = np.array([base[s]["rms"]["a"] / base[s]["rms"]["e"] for s in seeds])
    rv = np.array([v[s]["rms"]["a"] / v[s]["rms"]["e"] for s in seeds])
    print(f, "seeds", seeds)
    print(
        " base ratios",
        np.round(rb, 2),
        "<=0.5:",
        int((rb <= 0.5).sum()),
        "median",
        round(float(np.median(rb)), 2),
        "pooled",
        round(pooled("", base), 3),
    )
    print(
        " var  ratios",
        np.round(rv, 2),
        "<=0.5:",
        int((rv <= 0.5).sum()),
        "median",
        round(float(np.median(rv)), 2),
        "pooled",
        round(pooled(tag, v), 3),
    )
