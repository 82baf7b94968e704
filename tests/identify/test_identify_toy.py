"""The statistics of ``identify`` on a toy sensor model that is exactly linear in H (fast, exact truth)."""

from __future__ import annotations

from typing import Any

import numpy as np

from model.identify import IdentifyOptions, Window, identify
from model.identify_problem import confidence
from model.inputs import InputSeries

N_STEPS = 60
TRUTH = np.array([88.21, 46.32, 68.49, 46.72, 52.13, 70.23, 16.54])


class LinearToy:
    """T(k, ch) = 20 + Σ_i H_i·G_i(k, ch): a stand-in for the reduced model with a known Jacobian."""

    h_box = (5.0, 200.0)

    def __init__(self) -> None:
        rng = np.random.default_rng(0)
        ramp = 1.0 - np.exp(-np.arange(N_STEPS + 1) / 20.0)
        self.g = ramp[None, :, None] * rng.uniform(0.0, 0.03, size=(7, 1, 32))
        self.calls = 0

    def simulate_sensors(self, h: np.ndarray, inputs: Any, t0: Any, *, load_scale: Any = None) -> np.ndarray:
        self.calls += 1
        return 20.0 + np.einsum("pi,ikc->pkc", np.atleast_2d(h), self.g)


def _window(toy: LinearToy, seed: int, sigma: float = 0.15) -> Window:
    clean = toy.simulate_sensors(TRUTH[None, :], None, 20.0)[0]
    noisy = clean + sigma * np.random.default_rng(seed).standard_normal(clean.shape)
    inputs = InputSeries.constant(N_STEPS, dt_s=10.0, ambient_c=20.0, q_front_w=0.0, q_rear_w=0.0)
    return Window(inputs, noisy, np.ones(32, dtype=bool), 20.0)


def test_confidence_matches_the_textbook_formula() -> None:
    rng = np.random.default_rng(1)
    jac = rng.standard_normal((200, 3))
    res = 0.5 * rng.standard_normal(200)
    conf = confidence(jac, res)
    sigma2 = res @ res / (200 - 3)
    np.testing.assert_allclose(conf.cov, sigma2 * np.linalg.inv(jac.T @ jac))
    np.testing.assert_allclose(conf.half_width, 1.959964 * np.sqrt(np.diag(conf.cov)))
    np.testing.assert_allclose(np.diag(conf.correlation), 1.0)


def test_hybrid_cis_cover_the_truth_about_95_percent_of_the_time() -> None:
    toy = LinearToy()
    hits, sigmas = [], []
    for seed in range(60):
        # model_error_c 0: the toy model made the data itself, so the noise is the only error
        opts = IdentifyOptions(hybrid_maxiter=3, model_error_c=0.0)
        res = identify(toy, _window(toy, seed), rng=seed, options=opts)
        hits.append((res.h_ci95[:, 0] <= TRUTH) & (res.h_ci95[:, 1] >= TRUTH))
        sigmas.append(res.sigma_c)
    coverage = float(np.mean(hits))
    assert 0.9 <= coverage <= 0.99, coverage  # 420 components: binomial sd ≈ 0.011
    assert abs(np.median(sigmas) - 0.15) < 0.005


def test_poorly_identified_flag_follows_the_ci_width() -> None:
    toy = LinearToy()
    toy.g[0] *= 0.01  # H1 barely affects any sensor
    res = identify(toy, _window(toy, 3), rng=3)
    assert not res.identified[0]
    assert np.all(res.identified[1:])
    width = (res.h_ci95[:, 1] - res.h_ci95[:, 0]) / 2 / res.h
    np.testing.assert_array_equal(res.identified, width <= IdentifyOptions().ci_threshold)


def test_nfev_counts_candidates_and_warm_start_cuts_it() -> None:
    toy = LinearToy()
    w = _window(toy, 7)
    cold = identify(toy, w, rng=7)
    warm = identify(toy, w, rng=7, warm_start=cold)
    assert warm.nfev < cold.nfev
    np.testing.assert_allclose(warm.h, cold.h, rtol=1e-5)
