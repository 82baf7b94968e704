"""The fixture offset in the probe filter (``service.estimate.probe``, pure): readings = growth(θ_true, F_k)
+ b_true + noise, with b_true a step after the third reading. A persistent step is tracked from its second
reading on without bending θ; a single outlier is still refused and makes no step; a replay of the stored
readings reproduces the live posterior (incl. b and the step decisions); without an offset the mechanics
come out as the filter without b gives them."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta

import numpy as np

from service.contracts.probe import ProbeMeasurement
from service.estimate.mechbook import fixture_offset
from service.estimate.probe import (
    ProbeState,
    ProbeTuning,
    absorb,
    predict,
    replay_state,
    start_state,
    take_reading,
)

AT = datetime(2026, 11, 29, 6, 0, tzinfo=UTC)
TUNING = ProbeTuning(gate_sigma=3.0, step_sigma=2.0, offset_sd_um=5.0, offset_q_um2_per_h=0.05)
FREE = np.array([2.0, 9.0, -3.0])  # feature rows at a hot spindle (as tests/service/test_probe_update.py)
HELD = np.array([1.0, -1.0, -2.5])
COMMISSIONED_SD = np.array([0.03, 0.02, 0.02])  # a commissioned machine's posterior 1σ (s, a_s, a_h)


def _features(rng: np.random.Generator) -> np.ndarray:
    """A feature row at a random thermal state (cold .. hot), the groups' shares varying with the duty."""
    return rng.uniform(0.2, 1.0) * np.vstack([FREE, HELD]) * rng.uniform(0.6, 1.4, size=(2, 3))


def _commissioned(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(θ_true, the commissioning's mean, its covariance): the mean one posterior 1σ off the truth."""
    truth = np.array([rng.uniform(0.1, 0.9), 1.0 + rng.normal(0, 0.03), 1.0 + rng.normal(0, 0.03)])
    return truth, truth + COMMISSIONED_SD * rng.normal(size=3), np.diag(COMMISSIONED_SD**2)


def _take(
    state: ProbeState, rng: np.random.Generator, truth: np.ndarray, b: float, k: int, sd: float
) -> tuple[ProbeState, ProbeMeasurement]:
    f = _features(rng)
    y = predict(f, truth)[0] + b + rng.normal(0.0, sd)
    at = AT + timedelta(minutes=30 * (k + 1))
    new, up = take_reading(state, f, y, sd**2, at.timestamp(), TUNING)
    m = ProbeMeasurement(
        at=at,
        axial_um=y,
        sd_um=sd,
        features=tuple(tuple(float(v) for v in r) for r in f),
        field_var_um2=0.0,
        predicted_um=up.predicted_um,
        sigma_um=up.sigma_um,
        innovation_um=up.innovation_um,
        accepted=up.accepted,
        offset_step=up.offset_step,
    )
    return new, m


def test_a_persistent_step_is_tracked_within_1_um_after_two_readings_and_theta_is_not_bent() -> None:
    tracked = steps = 0
    for seed in range(20):
        rng = np.random.default_rng(seed)
        truth, mean, cov = _commissioned(rng)
        state = start_state(mean, cov, AT.timestamp(), TUNING)
        for k in range(3):  # the fixture as commissioned
            state, _ = _take(state, rng, truth, 0.0, k, 0.5)
        assert abs(state.x[3]) < 1.5, (seed, state.x)
        theta_before, cov_before = state.mechanics
        outcomes = []
        for k in range(3, 5):  # a fixture re-clamped: +3 µm from the fourth reading on
            state, m = _take(state, rng, truth, 3.0, k, 0.5)
            outcomes.append((m.accepted, m.offset_step))
        tracked += abs(state.x[3] - 3.0) <= 1.0
        assert not outcomes[0][1], (seed, outcomes)  # the first reading of a step never makes one
        steps += outcomes[1] == (True, True)  # the second confirms it: a step of b
        theta_after, _ = state.mechanics
        bent = np.abs(theta_after - theta_before) / np.sqrt(np.diag(cov_before))
        assert np.all(bent < 1.0), (seed, bent)  # θ moved by less than its own 1σ
        assert abs(theta_after[0] - truth[0]) < 4.0 * COMMISSIONED_SD[0], (seed, theta_after, truth)
        off = fixture_offset(state)
        assert off is not None and off.sd_um < 1.0
    assert tracked >= 19, tracked
    assert steps >= 18, steps


def test_a_single_outlier_is_refused_and_makes_no_step() -> None:
    rng = np.random.default_rng(5)
    truth, mean, cov = _commissioned(rng)
    state = start_state(mean, cov, AT.timestamp(), TUNING)
    for k in range(4):
        state, _ = _take(state, rng, truth, 1.0, k, 0.5)
    b_before = state.x[3]
    state, crash = _take(state, rng, truth, 1.0 + 40.0, 4, 0.5)  # a chip under the setter
    assert not crash.accepted and not crash.offset_step and crash.sigma_ratio > 3.0
    assert state.x[3] == b_before and state.pending is not None
    state, normal = _take(state, rng, truth, 1.0, 5, 0.5)  # the fixture never moved
    assert normal.accepted and not normal.offset_step and state.steps == 0
    assert abs(state.x[3] - 1.0) < 0.75
    # two gated readings on opposite sides are two outliers, not a step
    state, up = _take(state, rng, truth, 1.0 + 30.0, 6, 0.5)
    state, down = _take(state, rng, truth, 1.0 - 30.0, 7, 0.5)
    assert not up.accepted and not down.accepted and state.steps == 0


def test_a_replay_of_the_stored_readings_reproduces_the_live_posterior() -> None:
    rng = np.random.default_rng(8)
    truth, mean, cov = _commissioned(rng)
    start = start_state(mean, cov, AT.timestamp(), TUNING)
    state, kept = start, []
    for k, b in enumerate([0.0, 0.0, 0.0, 40.0, 0.0, -4.0, -4.0, -4.0, -4.0]):  # an outlier, then a step
        state, m = _take(state, rng, truth, b, k, 0.8)
        kept.append(m)
    assert [m.offset_step for m in kept].count(True) == 1 and not kept[3].accepted
    again = replay_state(start, kept, TUNING)
    assert np.allclose(again.x, state.x, rtol=0, atol=1e-12)
    assert np.allclose(again.cov, state.cov, rtol=0, atol=1e-12)
    assert (again.t, again.absorbed, again.steps, again.pending) == (
        state.t,
        state.absorbed,
        state.steps,
        state.pending,
    )
    # the restored filter decides the next reading as the live one would have
    f, y = _features(rng), 0.0
    a = take_reading(again, f, y, 1.0, state.t + 1800, TUNING)[1]
    b = take_reading(state, f, y, 1.0, state.t + 1800, TUNING)[1]
    assert (a.accepted, a.offset_step, a.innovation_um) == (b.accepted, b.offset_step, b.innovation_um)
    assert np.allclose(a.x, b.x, rtol=0, atol=1e-12)


def test_without_an_offset_the_mechanics_are_as_without_b() -> None:
    """Readings with no offset: θ comes out as the 3-state filter gives it (b's prior 5 µm costs only what
    the first reading spends on b), b stays within its band around 0, and a state with no reading serves
    no offset (the growth as before the offset existed)."""
    for seed in range(10):
        rng = np.random.default_rng(100 + seed)
        truth, mean, cov = _commissioned(rng)
        state = start_state(mean, cov, AT.timestamp(), TUNING)
        assert fixture_offset(state) is None
        x3, p3 = mean.copy(), cov.copy()
        f_test = _features(rng)
        for k in range(8):
            f = _features(rng)
            y = predict(f, truth)[0] + rng.normal(0.0, 0.5)
            state, up = take_reading(state, f, y, 0.25, (AT + timedelta(hours=k)).timestamp(), TUNING)
            three = absorb(x3, p3, f, y, 0.25)
            assert up.accepted and three.accepted and not up.offset_step
            x3, p3 = three.x, three.cov
        theta, p_theta = state.mechanics
        assert abs(state.x[3]) <= 2.5 * np.sqrt(state.cov[3, 3]), (seed, state.x, state.cov[3, 3])
        y4 = predict(f_test, theta)[0] + state.x[3]
        assert abs(y4 - predict(f_test, x3)[0]) < 0.5, seed  # the same growth within the reading noise
        assert np.all(np.sqrt(np.diag(p_theta)) <= np.sqrt(np.diag(cov)) + 1e-12)  # never wider


def test_a_restarted_growth_server_serves_the_live_offset_and_mechanics() -> None:
    """The growth server restored with the stored readings (``MechanicsBook`` → ``replay_state``) holds the
    posterior the live filter had, the offset (with its step) included."""
    from typing import Any, cast

    from service.contracts.mechanics import MechanicsCalibration
    from service.serve.compensation import GrowthServer, probe_tuning
    from service.settings import CompensationSettings

    tuning = probe_tuning(CompensationSettings())
    assert tuning == TUNING  # the settings' defaults are the ones tested above
    rng = np.random.default_rng(21)
    truth, mean, cov = _commissioned(rng)
    cal = MechanicsCalibration(
        x=(float(mean[0]), float(mean[1]), float(mean[2])),
        cov=tuple(tuple(float(v) for v in r) for r in cov),
        at=AT,
        set_by="test",
        source="cli",
    )
    state, kept = start_state(mean, cov, AT.timestamp(), TUNING), []
    for k, b in enumerate([0.0, 0.0, 0.0, 5.0, 5.0, 5.0]):
        state, m = _take(state, rng, truth, b, k, 0.5)
        kept.append(m)
    assert state.steps == 1
    server = GrowthServer(cast(Any, None), mechanics=cal, probes=tuple(kept))
    got, off = server.mechanics, server.fixture_offset
    assert got is not None and off is not None
    assert np.allclose(got.mean, np.clip(state.x[:3], [0.0, 0.51, 0.51], [1.0, 1.49, 1.49]), atol=1e-12)
    assert off.um == state.x[3] and off.sd_um == np.sqrt(state.cov[3, 3]) and off.steps == 1
    assert off.readings == state.absorbed == got.report["probe_readings_absorbed"]
