"""The commissioning verdict on the restraint (issue 41 item 13): a nearly free mount is a result, not a
failure. Held out: an independent solver's spring mount of 1.4e10 Pa/m (restraint ≈ 0.016) was fitted at
0.018 [−0.030, 0.066] with α within its CI; a restraint within 0.02 of a bound was refused as "at its bound".
Only a fit pinned on a bound of its search (0 or 1) is."""

from __future__ import annotations

import numpy as np

from model.growthfit import PARAMS, MechanicsFitResult
from service.shell.commissioning import FitLimits, judge_fit


def _fit(restraint: float, sd: float = 0.024) -> MechanicsFitResult:
    x = np.array([restraint, 1.01, 0.98, 0.0, 0.05])
    sds = np.array([sd, 0.03, 0.03, 0.1, 0.05])
    residual = np.full(200, 0.3) * np.where(np.arange(200) % 2, 1.0, -1.0)
    return MechanicsFitResult(
        x=x,
        cov=np.diag(sds**2),
        sd=sds,
        ci95=np.c_[x - 1.96 * sds, x + 1.96 * sds],
        prior_sd=np.array([0.3, 0.05, 0.05, np.inf, np.inf]),
        residual_um=residual,
        residual_rms_um=0.3,
        residual_max_um=0.3,
        noise_um=0.3,
        n_used=200,
        fun=1.0,
        nfev=30,
        success=True,
        message="ok",
        names=PARAMS,
    )


def _running() -> np.ndarray:
    return np.arange(200) < 120


def test_a_nearly_free_mount_is_commissioned() -> None:
    explained, problems, _ = judge_fit(_fit(0.018), _running(), FitLimits())
    assert explained, problems


def test_a_nearly_held_mount_is_commissioned() -> None:
    explained, problems, _ = judge_fit(_fit(0.985), _running(), FitLimits())
    assert explained, problems


def test_a_fit_pinned_on_its_bound_is_not() -> None:
    for s, side in ((0.0, "free (0)"), (1.0, "held (1)")):
        explained, problems, _ = judge_fit(_fit(s), _running(), FitLimits())
        assert not explained and any(f"restraint at its bound {side}" in p for p in problems), problems
