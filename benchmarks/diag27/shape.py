# ruff: noqa
"""Diagnostic: per seed, the error's mean, linear drift and the rest (a product, e MLR, d true H)."""

import sys
import numpy as np

from benchmarks.diag27.decomp import OUT

tot = {}
for s in [int(x) for x in sys.argv[1:]]:
    z = np.load(f"{OUT}/seed{s}.npz")
    t = np.arange(z["err_a"].size) / 60.0  # h
    row = [str(s)]
    for arm in ("a", "d", "e"):
        if f"err_{arm}" not in z:
            continue
        e = z[f"err_{arm}"]
        A = np.c_[np.ones_like(t), t - t.mean()]
        c, *_ = np.linalg.lstsq(A, e, rcond=None)
        rest = e - A @ c
        rms = np.sqrt(np.mean(e**2))
        row.append(
            f"{arm}: rms {rms:.2f} mean {c[0]:+.2f} drift {c[1]:+.2f}/h rest {np.sqrt(np.mean(rest**2)):.2f}"
        )
        tot.setdefault(arm, []).append(
            (rms**2, c[0] ** 2, (c[1] ** 2) * np.mean((t - t.mean()) ** 2), np.mean(rest**2))
        )
    print(" | ".join(row))
for arm, v in tot.items():
    v = np.array(v).mean(0)
    print(
        f"{arm} pooled MS {v[0]:.3f}: mean² {v[1]:.3f} ({v[1] / v[0]:.0%}), drift {v[2]:.3f} ({v[2] / v[0]:.0%}), rest {v[3]:.3f} ({v[3] / v[0]:.0%})"
    )
