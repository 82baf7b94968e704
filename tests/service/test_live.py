"""The live FE state follows the measured inputs exactly like model.fem.simulate with the same H."""

from __future__ import annotations

import numpy as np
import pytest

from model.fem import build_fe_model, simulate, steady_state
from model.geometry import load_spindle
from model.inputs import inputs_from_operation
from service.estimate.live import LiveModel, LiveStateError

H = np.array([88.0, 46.0, 68.0, 47.0, 52.0, 70.0, 16.0])


@pytest.fixture(scope="module")
def coarse():
    spec = load_spindle()
    return spec, build_fe_model(spec, mesh_size_m=0.006)


def test_live_state_matches_fem_simulate_and_snapshots(coarse):
    spec, fe = coarse
    n = 60
    speed = np.r_[np.full(30, 3000.0), np.full(31, 5000.0)]
    torque = np.full(n + 1, 2.0)
    amb = np.linspace(22.0, 22.5, n + 1)
    live = LiveModel(fe, spec, h=H, snapshot_every_s=100.0)
    live.initialize(0.0, 22.0, (amb[0], speed[0], torque[0]))
    for k in range(1, n + 1):
        live.push(10.0 * k, ambient_c=amb[k], speed_rpm=speed[k], torque_nm=torque[k])
    inputs = inputs_from_operation(
        spec, dt_s=10.0, speed_rpm=speed[:-1], torque_nm=torque[:-1], ambient_c=amb[:-1]
    )
    ref = simulate(fe, H, inputs, 22.0)
    now = live.field_now()
    assert now.t == 600.0
    np.testing.assert_allclose(now.field_c, ref[-1], atol=1e-9)
    np.testing.assert_allclose(live.sensors_now(), fe.sensor_op @ ref[-1], atol=1e-9)
    assert ref[-1].max() > 23.0  # the bearings heated up: the comparison is not trivial
    snap = live.field_at(250.0)
    assert snap.t == 200.0
    np.testing.assert_allclose(snap.field_c, ref[20], atol=1e-9)
    assert live.first_snapshot_after(250.0).t == 300.0


def test_steady_state_and_held_inputs(coarse):
    spec, fe = coarse
    live = LiveModel(fe, spec, h=H)
    with pytest.raises(LiveStateError):
        live.field_now()
    live.initialize(0.0, 21.0, (21.0, 4000.0, 3.0))
    live.push(10.0, ambient_c=21.0, speed_rpm=float("nan"), torque_nm=float("nan"))  # CAN down: held
    inputs = inputs_from_operation(spec, dt_s=1.0, speed_rpm=4000.0, torque_nm=3.0, ambient_c=21.0)
    ref = steady_state(fe, H, ambient_c=21.0, q_front_w=inputs.q_front_w[0], q_rear_w=inputs.q_rear_w[0])
    np.testing.assert_allclose(live.steady(), ref, atol=1e-9)
    live.set_h(H * 1.5)
    assert not np.allclose(live.steady(), ref, atol=1e-3)


def test_mark_keeps_the_field_at_a_past_condition_start(coarse):
    spec, fe = coarse
    live = LiveModel(fe, spec, h=H, snapshot_every_s=600.0, recent_steps=10)
    live.initialize(0.0, 22.0, (22.0, 3000.0, 2.0))
    fields = {}
    for k in range(1, 20):
        live.push(10.0 * k, ambient_c=22.0, speed_rpm=3000.0 if k < 12 else 5000.0, torque_nm=2.0)
        fields[10.0 * k] = live.field_now().field_c
    assert live.field_at(123.0).t == 0.0  # only the initial periodic snapshot so far
    snap = live.mark(123.0)
    assert snap.t == 120.0
    np.testing.assert_allclose(live.field_at(123.0).field_c, fields[120.0])
    assert live.first_snapshot_after(5.0).t == 120.0


def test_jittered_samples_step_on_the_grid_without_refactorising(coarse):
    spec, fe = coarse
    live = LiveModel(fe, spec, h=H, dt_s=10.0)
    live.initialize(0.0, 22.0, (22.0, 3000.0, 2.0))
    live.set_h(H, stepper=live.prepare(H))
    stepper = live._stepper
    rng = np.random.default_rng(0)
    for k in range(1, 30):
        live.push(10.0 * k + rng.uniform(-3, 3), ambient_c=22.0, speed_rpm=3000.0, torque_nm=2.0)
    assert live._stepper is stepper and live.steps == 29 and live.t == 290.0
    live.push(
        290.0 + 600.0, ambient_c=22.0, speed_rpm=3000.0, torque_nm=2.0
    )  # a 10 min gap: 60 steps at once
    assert live.t == 890.0 and live.steps == 89
    inputs = inputs_from_operation(
        spec, dt_s=10.0, speed_rpm=3000.0, torque_nm=2.0, ambient_c=np.full(89, 22.0)
    )
    np.testing.assert_allclose(live.field_now().field_c, simulate(fe, H, inputs, 22.0)[-1], atol=1e-9)


def test_a_window_inherits_the_covariance_of_the_last_rebase_before_it(coarse):
    """``covariance_at`` is opaque bookkeeping: the latest rebase at or before t, None before any, and a
    rebase without one (or an earlier rebase) hides the older ones from later windows."""
    from types import SimpleNamespace

    spec, fe = coarse
    live = LiveModel(fe, spec, h=H, snapshot_every_s=60.0)
    live.initialize(0.0, 22.0, (22.0, 3000.0, 2.0))
    for k in range(1, 31):
        live.push(10.0 * k, ambient_c=22.0, speed_rpm=3000.0, torque_nm=2.0)
    times = np.arange(0.0, 301.0, 10.0)
    raw = SimpleNamespace(
        times_s=times, ambient_c=np.full(31, 22.0), speed_rpm=np.full(31, 3000.0), torque_nm=np.full(31, 2.0)
    )
    field = live.field_now().field_c
    assert live.covariance_at(250.0) is None  # only the initial guess so far
    live.rebase(100.0, field, raw, covariance="cov@100")
    live.rebase(200.0, field, raw, covariance="cov@200")
    assert live.covariance_at(50.0) is None
    assert live.covariance_at(150.0) == "cov@100"
    assert live.covariance_at(250.0) == "cov@200"
    live.rebase(150.0, field, raw)  # an earlier rebase replaces what came after it
    assert live.covariance_at(250.0) is None and live.covariance_at(120.0) == "cov@100"
    assert live.t == pytest.approx(300.0)
    live.initialize(400.0, 22.0, (22.0, 3000.0, 2.0))
    assert live.covariance_at(450.0) is None


def test_a_rebase_gives_the_same_state_whether_it_comes_at_once_or_samples_later(coarse):
    """Jittered sample times: a rebase at a window end t must use the inputs of the sample within half a
    step of t, whether that sample came just before or just after t, and whether the identification
    finished at once (offline) or several samples later (the worker process). It once skipped the rebase
    when no sample lay in [t, now], so a replay and ``chtc identify`` started later windows differently."""
    from types import SimpleNamespace

    spec, fe = coarse
    rng = np.random.default_rng(1)
    grid = 10.0 * np.arange(1, 41)
    times = grid + rng.uniform(-4.0, 4.0, 40)
    speed = np.where(grid < 100.0, 3000.0, 5000.0)  # the step comes with the sample of the rebase time, 100 s

    def raw_between(t_from: float, t_to: float) -> SimpleNamespace:
        k = (times >= t_from) & (times <= t_to)
        n = int(k.sum())
        return SimpleNamespace(
            times_s=times[k], ambient_c=np.full(n, 22.0), speed_rpm=speed[k], torque_nm=np.full(n, 2.0)
        )

    def run(finish_after: int) -> np.ndarray:
        live = LiveModel(fe, spec, h=H, dt_s=10.0)
        live.initialize(0.0, 22.0, (22.0, 3000.0, 2.0))
        done = False
        for k, t in enumerate(times):
            live.push(float(t), ambient_c=22.0, speed_rpm=float(speed[k]), torque_nm=2.0)
            if not done and t >= 100.0 - 5.0 and k >= int(np.searchsorted(times, 95.0)) + finish_after:
                live.set_h(H * 1.3)
                live.rebase(100.0, np.full(fe.n_nodes, 25.0), raw_between(95.0, float(t)))
                done = True
        assert live.t == pytest.approx(400.0)
        return live.field_now().field_c

    at_once, later, much_later = run(0), run(1), run(5)
    np.testing.assert_allclose(later, at_once, atol=1e-9)
    np.testing.assert_allclose(much_later, at_once, atol=1e-9)
    # the reference: from the rebased field at 100 s with the new H and the grid-aligned inputs
    inputs = inputs_from_operation(
        spec,
        dt_s=10.0,
        speed_rpm=np.full(30, 5000.0),
        torque_nm=np.full(30, 2.0),
        ambient_c=np.full(30, 22.0),
    )
    np.testing.assert_allclose(at_once, simulate(fe, H * 1.3, inputs, 25.0)[-1], atol=1e-9)
    # no sample in the replayed range: the state still restarts from the given field (it was left unchanged)
    live = LiveModel(fe, spec, h=H, dt_s=10.0)
    live.initialize(0.0, 22.0, (22.0, 3000.0, 2.0))
    live.push(float(times[0]), ambient_c=22.0, speed_rpm=3000.0, torque_nm=2.0)
    live.rebase(10.0, np.full(fe.n_nodes, 25.0), raw_between(1e9, 1e9))
    assert live.t == 10.0 and np.all(live.field_now().field_c == 25.0)
