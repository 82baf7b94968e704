"""The start field's uncertainty carried through a window (``model.carry``): checked against refits and
against the reduced model's own trajectories, on virtual-plant data (finer mesh, its own truth)."""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np
import pytest

from model import carry
from model.identify import IdentificationError, identify
from model.identify_problem import Layout, Problem, usable_entries
from tests.identify.conftest import Condition


def _problem(model: Any, w: Any) -> Problem:
    usable = usable_entries(np.asarray(w.measured_c), w.mask)
    bounds = np.array([model.rom.h_box] * 7, dtype=float)
    return Problem(
        model.rom,
        inputs=w.inputs,
        measured_c=w.measured_c,
        usable=usable,
        t0=w.t0,
        bounds=bounds,
        layout=Layout(),
    )


def _direction(model: Any, seed: int, size_c: float = 0.3) -> np.ndarray:
    u = np.random.default_rng(seed).normal(size=model.rom.rank)
    return np.asarray(u * size_c / np.linalg.norm(u))


def test_a_zero_start_covariance_changes_nothing_but_reports_the_end_covariance(
    model: Any, cond3000: Condition
) -> None:
    r = model.rom.rank
    plain = identify(model.rom, cond3000.window, rng=0, spec=model.spec)
    exact = identify(model.rom, cond3000.window, rng=0, spec=model.spec, start_cov=np.zeros((r, r)))
    np.testing.assert_allclose(exact.h_ci95, plain.h_ci95)
    assert plain.end_cov is None and exact.end_cov is not None
    lam = np.linalg.eigvalsh(exact.end_cov)
    assert lam.min() > -1e-12 * lam.max() and lam.max() > 0.0  # the window's own noise reaches the end


def test_the_gain_predicts_a_refit_from_a_perturbed_start(model: Any, cond3000: Condition) -> None:
    w = cond3000.window
    base = identify(model.rom, w, rng=0, spec=model.spec)
    for seed in (1, 2):
        u = _direction(model, seed)
        widened = identify(model.rom, w, rng=0, spec=model.spec, start_cov=np.outer(u, u))
        start = np.full(model.rom.n_nodes, float(w.t0)) + model.rom.lift(u)
        refit = identify(model.rom, replace(w, t0=start), rng=0, spec=model.spec, warm_start=base.h)
        moved = np.abs(refit.h - base.h)
        half = lambda res: (res.h_ci95[:, 1] - res.h_ci95[:, 0]) / 2  # noqa: E731
        predicted = np.sqrt(np.maximum(half(widened) ** 2 - half(base) ** 2, 0.0)) / 1.959964
        big = moved > 0.05 * moved.max()
        np.testing.assert_allclose(predicted[big], moved[big], rtol=0.15)


def test_the_end_covariance_follows_the_trajectories(model: Any, cond3000: Condition) -> None:
    w = cond3000.window
    res = identify(model.rom, w, rng=0, spec=model.spec)
    problem = _problem(model, w)
    u = _direction(model, 3)
    n = len(w.inputs.ambient_c)
    # the propagator is the difference of two trajectories from starts u apart
    a = model.rom.simulate_state(res.h, w.inputs, w.t0)[-1]
    start = np.full(model.rom.n_nodes, float(w.t0)) + model.rom.lift(u)
    b = model.rom.simulate_state(res.h, w.inputs, start)[-1]
    e = carry.propagator(model.rom, res.h, w.inputs.dt_s, n)
    np.testing.assert_allclose(e @ u, b - a, atol=1e-9)
    # the sensor responses are the same difference seen at the sensors
    ya = model.rom.simulate_sensors(res.h[None, :], w.inputs, w.t0)[0]
    yb = model.rom.simulate_sensors(res.h[None, :], w.inputs, start)[0]
    resp = carry.start_responses(model.rom, res.h, w.inputs.dt_s, n, u[:, None])[0]
    np.testing.assert_allclose(resp, yb - ya, atol=1e-9)
    # end covariance = moved start + the parameters' noise, through S = ∂a_end/∂θ
    jac, _ = problem.jacobian(res.theta)
    carried = carry.carry(problem, res.theta, jac, np.zeros((7, 7)), np.outer(u, u))
    gain = -np.linalg.solve(jac.T @ jac, jac.T @ problem.select(resp[None])[0])
    s = np.column_stack(
        [
            (model.rom.simulate_state(res.h + 1e-3 * np.eye(7)[i], w.inputs, w.t0)[-1] - a) / 1e-3
            for i in range(7)
        ]
    )
    moved = e @ u + s @ gain
    np.testing.assert_allclose(carried.end_cov, np.outer(moved, moved), atol=1e-3 * np.abs(moved).max() ** 2)


def test_propagate_decays_to_the_window_start_and_never_grows(model: Any) -> None:
    r = model.rom.rank
    u = _direction(model, 4)
    sc = carry.StateCovariance(1000.0, np.outer(u, u), np.full(7, 60.0))
    same = carry.propagate(model.rom, sc, 1000.0, 10.0)
    np.testing.assert_allclose(same, np.outer(u, u))
    later = carry.propagate(model.rom, sc, 1000.0 + 600.0, 10.0)
    assert np.trace(later) < np.trace(same)
    assert (
        carry.propagate(model.rom, carry.StateCovariance(0.0, np.zeros((r, r)), sc.h), 50.0, 10.0).max() == 0
    )


def test_bad_start_covariances_name_the_argument(model: Any, cond3000: Condition) -> None:
    with pytest.raises(IdentificationError, match="start_cov"):
        identify(model.rom, cond3000.window, rng=0, spec=model.spec, start_cov=np.zeros((3, 3)))
    bad = np.zeros((model.rom.rank,) * 2)
    bad[0, 0] = np.nan
    with pytest.raises(IdentificationError, match="start_cov"):
        identify(model.rom, cond3000.window, rng=0, spec=model.spec, start_cov=bad)
