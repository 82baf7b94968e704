"""The reduced model over windows whose H change from segment to segment (model.rom_segments)."""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np
import pytest

from model import rom_modal
from model import rom_segments as rs
from model.inputs import InputSeries, inputs_from_operation
from model.rom_segments import SegmentError, SegmentPlan


def _window(spec: Any, n_seg: int = 12, seed: int = 0) -> tuple[SegmentPlan, InputSeries, np.ndarray]:
    rng = np.random.default_rng(seed)
    lengths = 1 + rng.multinomial(120 - n_seg, np.ones(n_seg) / n_seg)
    speeds = np.repeat(np.arange(n_seg) * 500.0 + 500.0, lengths)  # consecutive speeds differ
    inputs = inputs_from_operation(
        spec, dt_s=10.0, speed_rpm=speeds, torque_nm=np.repeat(rng.uniform(3, 15, n_seg), lengths),
        ambient_c=22.0 + 0.5 * np.sin(np.arange(speeds.size) / 30.0),
    )  # fmt: skip
    return rs.plan_from_speed(speeds), inputs, rng.uniform(8.0, 150.0, (n_seg, 7))


def test_plan_from_speed() -> None:
    plan = rs.plan_from_speed([0.0, 0.0, 3000.0, 3000.0, 3000.0, 0.0])
    np.testing.assert_array_equal(plan.start, [0, 2, 5])
    np.testing.assert_array_equal(plan.of_step, [0, 0, 1, 1, 1, 2])
    np.testing.assert_allclose(rs.segment_means(plan, [1, 3, 2, 2, 5, 7]), [2.0, 3.0, 7.0])


# the ROM's own step: 0 exact over each held step (the service's default), 1 the θ-step, 3 three θ-substeps
SUBSTEPS = [0, 1, 3]


@pytest.mark.parametrize("substeps", SUBSTEPS)
def test_one_h_for_all_segments_is_the_reduced_model(model: Any, substeps: int) -> None:
    plan, inputs, h = _window(model.spec)
    # the all-exact evaluation (n_slow 0): at substeps 0 the served one is the spectral split
    # (model.rom_split), within a few mK of it (tests/model_rom/test_rom_split.py)
    rom = replace(model.rom, substeps=substeps, n_slow=0)
    same = np.repeat(h[:1], plan.n_segments, axis=0)[None]
    ours = rs.simulate_sensors(rom, same, plan, inputs, 21.0)
    ref = rom.simulate_sensors(h[:1], inputs, 21.0)
    np.testing.assert_allclose(ours, ref, atol=1e-9)


def test_switching_h_matches_the_full_fe_to_the_rom_accuracy(model: Any) -> None:
    """Full FE with K(H_s) switched at each segment start (field carried over) vs the reduced model."""
    plan, inputs, h = _window(model.spec)
    ours = rs.simulate_sensors(model.rom, h[None], plan, inputs, 21.0)[0]
    ref, _ = rs.fe_sensors(model.fe, h, plan, inputs, 21.0, theta=model.rom.theta)
    assert (ref - 21.0).max() > 3.0  # the window heats the spindle: the comparison is not trivial
    assert np.abs(ours - ref).max() <= 1.5 * model.rom.error_report["max_err_c"]


def test_population_equals_single_runs(model: Any) -> None:
    plan, inputs, h = _window(model.spec)
    pop = np.stack([h, h * 0.7, h * 1.3])
    out = rs.simulate_sensors(model.rom, pop, plan, inputs, 21.0)
    assert out.shape == (3, plan.n_steps + 1, 32)
    for p in range(3):
        np.testing.assert_allclose(
            out[p], rs.simulate_sensors(model.rom, pop[p : p + 1], plan, inputs, 21.0)[0]
        )


@pytest.mark.parametrize("substeps", SUBSTEPS)
def test_tangents_are_the_derivative(model: Any, substeps: int) -> None:
    plan, inputs, h = _window(model.spec)
    rom = replace(model.rom, substeps=substeps)
    dh = np.random.default_rng(1).normal(size=(3, plan.n_segments, 7))
    tg = rs.simulate_tangents(rom, h, dh, plan, inputs, 21.0)
    eps = 1e-4
    plus = rs.simulate_sensors(rom, h[None] + eps * dh, plan, inputs, 21.0)
    minus = rs.simulate_sensors(rom, h[None] - eps * dh, plan, inputs, 21.0)
    fd = (plus - minus) / (2 * eps)
    assert np.abs(tg.d_sensors).max() > 1e-3
    np.testing.assert_allclose(tg.d_sensors, fd, atol=1e-8)
    np.testing.assert_allclose(tg.sensors, rs.simulate_sensors(rom, h[None], plan, inputs, 21.0)[0])


def test_tangents_from_given_states_are_the_same(model: Any) -> None:
    """The caller's run of the same H (``run=``) gives the tangents computed from scratch; a run of
    another window or of a population is refused."""
    plan, inputs, h = _window(model.spec)
    dh = np.random.default_rng(2).normal(size=(2, plan.n_segments, 7))
    run = rs.simulate_run(model.rom, h[None], plan, inputs, 21.0)
    np.testing.assert_array_equal(run[0], rs.simulate_states(model.rom, h[None], plan, inputs, 21.0))
    given = rs.simulate_tangents(model.rom, h, dh, plan, inputs, 21.0, run=run)
    fresh = rs.simulate_tangents(model.rom, h, dh, plan, inputs, 21.0)
    np.testing.assert_array_equal(given.d_sensors, fresh.d_sensors)
    np.testing.assert_array_equal(given.sensors, fresh.sensors)
    two = rs.simulate_run(model.rom, np.stack([h, h]), plan, inputs, 21.0)
    with pytest.raises(SegmentError, match="run"):
        rs.simulate_tangents(model.rom, h, dh, plan, inputs, 21.0, run=two)


def test_loewner_matrix_gives_the_derivative_of_a_matrix_function() -> None:
    """Daleckii–Krein on a small SPD matrix with two nearly equal eigenvalues, against central differences."""
    rng = np.random.default_rng(4)
    q, _ = np.linalg.qr(rng.normal(size=(4, 4)))
    k = (q * np.array([0.01, 0.02, 0.02 + 1e-13, 0.3])) @ q.T
    e = rng.normal(size=(4, 4))
    e = e + e.T
    for substeps in SUBSTEPS:

        def f(m: np.ndarray, which: int, substeps: int = substeps) -> np.ndarray:
            lam, phi = np.linalg.eigh(m)
            vals = rom_modal.step_factors(lam, 10.0, 1.0, substeps)[which]
            return np.asarray((phi * vals) @ phi.T)

        lam, phi = np.linalg.eigh(k)
        mu, gamma = rom_modal.step_factors(lam, 10.0, 1.0, substeps)
        dmu, dgamma = rs.step_derivatives(lam, 10.0, 1.0, substeps)
        for which, (vals, dvals) in enumerate(((mu, dmu), (gamma, dgamma))):
            exact = phi @ (rs.loewner(lam, vals, dvals) * (phi.T @ e @ phi)) @ phi.T
            eps = 1e-6
            fd = (f(k + eps * e, which) - f(k - eps * e, which)) / (2 * eps)
            np.testing.assert_allclose(exact, fd, atol=1e-7 * np.abs(fd).max())


def test_errors_name_the_argument(model: Any) -> None:
    plan, inputs, h = _window(model.spec)
    with pytest.raises(SegmentError, match="h_seg"):
        rs.simulate_sensors(model.rom, h, plan, inputs, 21.0)
    with pytest.raises(SegmentError, match="h_seg"):
        rs.simulate_sensors(model.rom, -h[None], plan, inputs, 21.0)
    with pytest.raises(SegmentError, match=r"inputs\.ambient_c"):
        rs.simulate_sensors(model.rom, h[None], plan, inputs.slice(0, 10), 21.0)
    with pytest.raises(SegmentError, match="dh_seg"):
        rs.simulate_tangents(model.rom, h, h, plan, inputs, 21.0)
    with pytest.raises(SegmentError, match="speed_rpm"):
        rs.plan_from_speed([])
