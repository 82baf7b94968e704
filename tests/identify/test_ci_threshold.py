"""Why the "identified" threshold is 0.5 and not the 30 % docs/design/identification.md used to state (issue
12, item 12): on the best case the product meets (one 60-min condition, all 32 channels, σ = 0.15 °C; the
bench's two conditions × 20 noise seeds, hybrid), a 30 % threshold never lets H1 pass (its achievable 1σ
precision is ~15 %, SPEC §3). At 0.5 the well-determined H3, H5, H6, H7 are identified in every window and the
identified H are covered by their CIs; since the model-error term H2/H4 never pass
(docs/design/identification.md). ~30 s."""

from __future__ import annotations

import argparse

import numpy as np
import pytest

from benchmarks.identify import _load, _noisy
from model.identify import IdentifyOptions, identify

pytestmark = pytest.mark.slow


def test_threshold_measured_on_the_bench_conditions() -> None:
    model, data = _load(argparse.Namespace())
    rel, covered = [], []
    for d in data:
        for seed in range(20):
            r = identify(model.rom, _noisy(d, 500 + seed), rng=seed, spec=model.spec)
            lo, hi = r.h_ci95[:, 0], r.h_ci95[:, 1]
            rel.append(np.log(hi / r.h))  # 1.96·σ(log H)
            covered.append((lo <= d.h_true) & (d.h_true <= hi))
    rel_a, cov_a = np.array(rel), np.array(covered)
    at_30, at_50 = rel_a <= 0.3, rel_a <= IdentifyOptions().ci_threshold
    assert IdentifyOptions().ci_threshold == 0.5
    assert at_30[:, 0].mean() < 0.1 and at_30.all(axis=1).mean() < 0.1  # H1 (almost) never, so never usable
    # With the model-error term (0.02 °C, issue 15) H3, H5, H6, H7 pass 0.5 in every window (measured 1.0) and
    # H2/H4 never: no window has all seven (docs/design/identification.md; the usable rule is open).
    assert (at_50[:, [2, 4, 5, 6]].mean(axis=0) >= 0.9).all()
    assert cov_a[at_50].mean() >= 0.9 and cov_a.mean() >= 0.9  # measured 1.0 and 1.0 (2026-11-24)
