"""The filtered state's covariance stays a covariance (docs/design/estimator.md, "Covariance health").

The bug (2026-11-27, the simulated ISO 230-3 thermal test ``python -m simulator.thermaltest --short
--seed 4`` commissioned through the core): an identification's ``set_h`` with a narrower CI lowered the
considered H errors' 1σ while their cross-covariance with the state was kept, so the next predictions made
P indefinite (negative variances, negative NIS) and the served field reached 165 °C, still "converged".
Data here: the service's own reduced model run open loop with noise 0.15 °C (what matters is the covariance
algebra, not the model's truth), warming up at 7000 rpm, then a new H with a 5 % CI.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from model.estimator import Estimate, StepInput, predict_mean, transition
from model.inputs import inputs_from_operation
from service.estimate.state import FilteredState

H_TRUE = np.array([88.21, 46.32, 68.49, 46.72, 52.13, 70.23, 16.54])
H_GUESS = np.full(7, 50.0)  # the service's initial_h, considered 100 % off until an identification
DT = 10.0
AMBIENT = 21.0


def _warm_up(model: Any, n_idle: int, n_run: int, seed: int = 4) -> list[dict[str, Any]]:
    """Samples of the reduced model with the true H: ``n_idle`` at rest, then ``n_run`` at 7000 rpm, 5 N·m."""
    rom, spec = model.rom, model.spec
    speed = np.r_[np.zeros(n_idle), np.full(n_run, 7000.0)]
    torque = np.r_[np.zeros(n_idle), np.full(n_run, 5.0)]
    inp = inputs_from_operation(
        spec, dt_s=DT, speed_rpm=speed, torque_nm=torque, ambient_c=np.full(speed.size, AMBIENT)
    )
    tr = transition(rom, H_TRUE, DT)
    a = rom.steady_state(H_TRUE, ambient_c=AMBIENT, q_front_w=0.0, q_rear_w=0.0)
    rng = np.random.default_rng(seed)
    out = []
    for k in range(speed.size):
        if k:  # the previous sample's inputs held over the step (FilteredState.push's convention)
            u = StepInput(H_TRUE, AMBIENT, float(inp.q_front_w[k - 1]), float(inp.q_rear_w[k - 1]), DT)
            a = predict_mean(tr, a, u)
        temps = np.asarray(rom.sensors) @ a + rng.normal(0.0, 0.15, 32)
        out.append({"ambient_c": AMBIENT, "speed_rpm": speed[k], "torque_nm": torque[k], "temps_c": temps})
    return out


def _min_eig_rel(est: Estimate) -> float:
    """Smallest eigenvalue of P over its largest variance."""
    return float(np.linalg.eigvalsh(est.cov)[0] / np.diagonal(est.cov).max())


def test_a_narrower_h_ci_keeps_the_covariance_positive_and_the_field_physical(loaded_model: Any) -> None:
    """set_h with h_rel 1.0 → 0.05 on a warming spindle: P stays positive semi-definite (before the fix its
    smallest eigenvalue fell to −5e-3 × its largest variance within 10 min), the state neither restarts nor
    leaves the physical range, and the NIS stays positive."""
    samples = _warm_up(loaded_model, 6, 120)
    state = FilteredState(loaded_model.rom, loaded_model.spec, h=H_GUESS)
    state.set_h(H_GUESS, h_rel=1.0)
    s0 = samples[0]
    state.initialize(0.0, (s0["ambient_c"], s0["speed_rpm"], s0["torque_nm"]), s0["temps_c"])
    worst, nis_min = 0.0, np.inf
    for k, s in enumerate(samples[1:], start=1):
        if k == 66:  # an identification 10 min into the run: the true H, 5 % CI
            state.set_h(H_TRUE, h_rel=0.05)
        upd = state.push(k * DT, **s)
        assert not upd.restarted, upd.reason
        worst = min(worst, _min_eig_rel(state.estimator.estimate))
        nis_min = min(nis_min, upd.nis)
        assert float(state.field_now().field_c.max()) < 60.0, k
    assert worst > -1e-9, worst
    assert nis_min >= 0.0
    assert state.converged_at is not None
    assert np.all(np.isfinite(state.field_std_now()))


@pytest.mark.parametrize("kind", ["negative variance", "indefinite", "non-finite"])
def test_a_belief_that_is_no_distribution_is_never_served_converged(loaded_model: Any, kind: str) -> None:
    """Whatever broke it, a covariance with a negative or non-finite variance, or one not positive
    semi-definite, restarts the state from the prior on that sample: not converged, ``reason`` says why."""
    samples = _warm_up(loaded_model, 12, 0)
    state = FilteredState(loaded_model.rom, loaded_model.spec, h=H_TRUE)
    s0 = samples[0]
    state.initialize(0.0, (s0["ambient_c"], s0["speed_rpm"], s0["torque_nm"]), s0["temps_c"])
    for k in range(1, 10):
        state.push(k * DT, **samples[k])
    assert state.converged_at is not None
    est = state.estimator.estimate
    cov = est.cov.copy()
    if kind == "negative variance":
        cov[3, 3] = -abs(cov[3, 3]) - 1.0
    elif kind == "indefinite":  # every variance still > 0, but a correlation of 2 between two coordinates
        cov[0, 1] = cov[1, 0] = 2.0 * np.sqrt(cov[0, 0] * cov[1, 1])
    else:
        cov[0, 0] = np.nan
    state.estimator.estimate = Estimate(est.mean, cov, est.cross)
    upd = state.push(10 * DT, **samples[10])
    assert upd.restarted and upd.reason.startswith("covariance:"), upd.reason
    assert state.converged_at is None and not state.view().converged
    assert state.last_restart == (10 * DT, upd.reason)
    assert _min_eig_rel(state.estimator.estimate) > -1e-9


def test_a_checkpoint_resumed_under_a_narrower_h_ci_stays_positive(loaded_model: Any) -> None:
    """A checkpoint written with the considered H errors at 100 %, resumed after ``set_h`` with 5 % (the
    core sets the stored result's CI before ``resume``): the cross-covariance is rescaled to the new 1σ, and
    the resumed state keeps a positive semi-definite P without restarting (without the rescale: a negative
    variance at the first sample, and a restart). A checkpoint without ``param_std`` (written before it was
    kept) still loads."""
    from service.contracts.checkpoint import LiveCheckpoint

    samples = _warm_up(loaded_model, 6, 72)
    state = FilteredState(loaded_model.rom, loaded_model.spec, h=H_GUESS)
    state.set_h(H_GUESS, h_rel=1.0)
    s0 = samples[0]
    state.initialize(0.0, (s0["ambient_c"], s0["speed_rpm"], s0["torque_nm"]), s0["temps_c"])
    for k in range(1, 66):
        state.push(k * DT, **samples[k])
    cp = state.checkpoint("m1")
    assert cp.param_std is not None and np.all(cp.param_std[:7] == 1.0)
    stored = LiveCheckpoint.from_parts(
        cp.to_bytes(), t=cp.t, model_version="m1", converged=cp.converged, inputs=cp.inputs
    )
    resumed = FilteredState(loaded_model.rom, loaded_model.spec, h=H_TRUE)
    resumed.set_h(H_TRUE, h_rel=0.05)
    resumed.resume(stored, "m1")
    for k in range(66, 72):
        upd = resumed.push(k * DT, **samples[k])
        assert not upd.restarted, upd.reason
        assert _min_eig_rel(resumed.estimator.estimate) > -1e-9
    old = LiveCheckpoint(**{**cp.__dict__, "param_std": None})
    again = LiveCheckpoint.from_parts(
        old.to_bytes(), t=cp.t, model_version="m1", converged=cp.converged, inputs=cp.inputs
    )
    assert again.param_std is None
    np.testing.assert_array_equal(again.cross, cp.cross)
