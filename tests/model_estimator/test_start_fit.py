"""Fitting the start state's uncertain directions inside the identification (model.identify.StartFitProblem):
the algebra of the profiled (variable-projection) start coefficients."""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np
import pytest

from model.identify import IdentifyOptions, StartFitProblem, Window, identify, split_start_cov
from model.identify_problem import usable_entries
from model.inputs import InputSeries

H = np.array([88.21, 46.32, 68.49, 46.72, 52.13, 70.23, 16.54])


def _inputs(n: int = 90) -> InputSeries:
    k = np.arange(n)
    return InputSeries(10.0, np.full(n, 22.0), np.where(k < 20, 60.0, 150.0), np.full(n, 70.0))


def _cov(rom: Any) -> np.ndarray:
    rng = np.random.default_rng(2)
    b = rng.normal(size=(rom.rank, rom.rank)) * np.exp(-0.3 * np.arange(rom.rank))[None, :]
    return np.asarray(b @ b.T)


def test_split_start_cov_keeps_the_leading_directions_and_the_rest(model: Any) -> None:
    cov = _cov(model.rom)
    u, rest = split_start_cov(cov, 3)
    np.testing.assert_allclose(u @ u.T + rest, cov, atol=1e-10 * np.abs(cov).max())
    lam = np.sort(np.linalg.eigvalsh(cov))[::-1]
    np.testing.assert_allclose(np.sort(np.linalg.eigvalsh(u @ u.T))[::-1][:3], lam[:3], rtol=1e-9)
    assert np.linalg.eigvalsh(rest).max() == pytest.approx(lam[3], rel=1e-9)


def test_profiled_start_is_the_ridge_solution_and_a_real_model_run(model: Any) -> None:
    """The profiled prediction is the reduced model run from a₀ + U·ĉ, and ĉ minimises
    ‖r₀ + D·c‖² + σ²‖c‖² (its gradient vanishes; a perturbed c is worse). On the all-exact evaluation
    (n_slow 0): the start responses are exact modal ones, the served spectral split is within a few mK."""
    rom, inputs = replace(model.rom, n_slow=0), _inputs()
    t0 = 22.0
    u, _ = split_start_cov(100.0 * _cov(rom), 4)
    truth_start = rom.initial_state(t0) + u @ np.array([1.0, -0.5, 0.3, 0.0])
    rng = np.random.default_rng(0)
    meas = rom.simulate_sensors((H * 1.1)[None], inputs, rom.lift(truth_start))[0]
    meas = meas + 0.15 * rng.standard_normal(meas.shape)
    bounds = np.array([[5.0, 200.0]] * 7)
    prob = StartFitProblem(
        rom, directions=u, noise_c=0.15, inputs=inputs, measured_c=meas,
        usable=usable_entries(meas, np.ones(32, bool)), t0=t0, bounds=bounds,
    )  # fmt: skip
    theta = np.stack([H, H * 1.1])
    pred = prob.predict(theta)
    coeffs = prob.last_coefficients
    for i in range(2):
        run = rom.simulate_sensors(theta[i : i + 1], inputs, rom.lift(rom.initial_state(t0) + u @ coeffs[i]))[
            0
        ]
        np.testing.assert_allclose(pred[i], run, atol=1e-8)

    def cost(c: np.ndarray, i: int) -> float:
        start = rom.lift(rom.initial_state(t0) + u @ c)
        r = prob.select(rom.simulate_sensors(theta[i : i + 1], inputs, start))[0] - prob._target
        return float(r @ r + 0.15**2 * c @ c)

    best = cost(coeffs[1], 1)
    for j in range(4):
        step = np.zeros(4)
        step[j] = 0.05
        assert cost(coeffs[1] + step, 1) > best and cost(coeffs[1] - step, 1) > best
    # at the true H the fit is at least as good as the true start, and clearly better than a₀
    assert best <= cost(np.array([1.0, -0.5, 0.3, 0.0]), 1) < cost(np.zeros(4), 1) - 1.0


def test_start_modes_zero_is_the_carry_alone(model: Any) -> None:
    """``start_modes`` 0 (the default) leaves ``identify`` as it was: identical answers."""
    rom, inputs = model.rom, _inputs(60)
    meas = rom.simulate_sensors(H[None], inputs, 22.0)[0] + 0.1 * np.random.default_rng(1).standard_normal(
        (61, 32)
    )
    w = Window(inputs, meas, np.ones(32, bool), 22.0)
    cov = _cov(rom) * 1e-3
    a = identify(rom, w, rng=0, start_cov=cov)
    b = identify(rom, w, rng=0, start_cov=cov, options=IdentifyOptions(start_modes=0))
    np.testing.assert_array_equal(a.h, b.h)
    np.testing.assert_array_equal(a.h_ci95, b.h_ci95)
    c = identify(rom, w, rng=0, start_cov=cov, options=IdentifyOptions(start_modes=2))
    assert not np.array_equal(a.h_ci95, c.h_ci95)
