"""Reduced model against the full θ-method on a small stand-in affine system."""

from __future__ import annotations

import inspect
from pathlib import Path

import numpy as np
import pytest

from model import rom_check, rom_train
from model.rom import DEFAULT_THETA, ReducedModel, RomError, load_or_build_rom

from ._toy import ToyFE, ToySpec

Inputs = rom_check.CaseInputs


def _inputs(n: int, *, amb: float = 20.0, qf: float = 150.0, qr: float = 80.0) -> Inputs:
    return Inputs(10.0, np.full(n, amb), np.full(n, qf), np.full(n, qr))


def _full(fe: ToyFE, h: np.ndarray, inputs: Inputs, t0: np.ndarray, scale=(1.0, 1.0)) -> np.ndarray:
    return rom_train.reference_sensors(
        fe,
        h,
        dt_s=inputs.dt_s,
        ambient_c=inputs.ambient_c,
        q_front_w=inputs.q_front_w,
        q_rear_w=inputs.q_rear_w,
        t0=t0,
        theta=DEFAULT_THETA,
        load_scale=scale,
    )


def _reduced_theta_steps(rom: ReducedModel, h: np.ndarray, inputs: Inputs, a0: np.ndarray) -> np.ndarray:
    """The reduced θ-method stepped naively (dense solves), independent of the modal closed form."""
    kr = rom.k0 + np.tensordot(h, rom.k_zone, axes=1)
    dt, th = inputs.dt_s, rom.theta
    lhs = np.eye(rom.rank) / dt + th * kr
    rhs = np.eye(rom.rank) / dt - (1 - th) * kr
    a = a0.copy()
    out = [a]
    for k in range(inputs.ambient_c.size):
        z = (
            inputs.ambient_c[k] * (h @ rom.z_zone)
            + inputs.q_front_w[k] * rom.q_front
            + inputs.q_rear_w[k] * rom.q_rear
        )
        a = np.linalg.solve(lhs, rhs @ a + z)
        out.append(a)
    return np.array(out)


def test_theta_default_matches_full_fe() -> None:
    from model.fem import simulate

    assert inspect.signature(simulate).parameters["theta"].default == DEFAULT_THETA


def test_reduced_mass_is_identity_and_uniform_field_exact(toy_rom: ReducedModel, toy_fe: ToyFE) -> None:
    er = toy_rom.basis.T @ (toy_fe.E @ toy_rom.basis)
    np.testing.assert_allclose(er, np.eye(toy_rom.rank), atol=1e-9)
    ones = np.ones(toy_rom.n_nodes)
    np.testing.assert_allclose(toy_rom.lift(toy_rom.project(ones)), ones, atol=1e-9)


def test_error_report_is_measured_and_small(toy_rom: ReducedModel) -> None:
    rep = toy_rom.error_report
    assert rep["n_histories"] == 12
    assert 0.0 < rep["max_err_c"] < 0.05
    assert rep["mean_err_c"] <= rep["max_err_c"]


def test_rom_matches_full_fe_on_unseen_random_cases(toy_rom: ReducedModel, toy_fe: ToyFE) -> None:
    rng = np.random.default_rng(2024)
    bound = toy_rom.error_report["max_err_c"]
    errs = []
    for i in range(4):
        case = rom_check.random_case(
            toy_fe, rng, box=toy_rom.h_box, n_steps=120, dt_s=10.0, q_max_w=(300.0, 150.0), log_h=i % 2 == 0
        )
        errs.extend(rom_check.case_errors(toy_rom, toy_fe, case, theta=toy_rom.theta))
    # unseen cases stay within the reported bound (with a margin for sampling) and within the target
    assert max(errs) < max(1.5 * bound, 1e-3)
    assert max(errs) < 0.05


def test_closed_form_equals_reduced_theta_stepping(toy_rom: ReducedModel) -> None:
    h = np.array([5.0, 200.0, 30.0, 80.0, 12.0, 150.0, 60.0])
    amb = np.r_[np.full(7, 20.0), np.full(13, 24.0)]
    qf = np.r_[np.full(3, 0.0), np.full(17, 200.0)]
    inputs = Inputs(10.0, amb, qf, np.linspace(0.0, 90.0, 20))  # rear heat changes every step
    a0 = toy_rom.initial_state(18.0)
    naive = _reduced_theta_steps(toy_rom, h, inputs, a0)
    np.testing.assert_allclose(toy_rom.simulate_state(h, inputs, 18.0), naive, atol=1e-9)


def test_batched_equals_looped(toy_rom: ReducedModel) -> None:
    rng = np.random.default_rng(3)
    h = rom_train.log_latin_hypercube(6, toy_rom.h_box, rng=rng)
    scale = rng.uniform(0.5, 1.5, (6, 2))
    inputs = rom_check.random_inputs(rng, n_steps=90, dt_s=10.0, q_max_w=(300.0, 150.0))
    batch = toy_rom.simulate_sensors(h, inputs, 21.0, load_scale=scale)
    assert batch.shape == (6, 91, 32)
    for p in range(6):
        one = toy_rom.simulate_sensors(h[p : p + 1], inputs, 21.0, load_scale=scale[p : p + 1])[0]
        np.testing.assert_allclose(batch[p], one, atol=1e-10)


def test_load_scale_is_linear_in_heat(toy_rom: ReducedModel, toy_fe: ToyFE) -> None:
    h = np.full((1, 7), 40.0)
    inputs = _inputs(60)

    def run(sf: float, sr: float) -> np.ndarray:
        return toy_rom.simulate_sensors(h, inputs, 20.0, load_scale=np.array([[sf, sr]]))[0]

    base, front, rear = run(0.0, 0.0), run(1.0, 0.0) - run(0.0, 0.0), run(0.0, 1.0) - run(0.0, 0.0)
    np.testing.assert_allclose(run(2.0, 0.5), base + 2.0 * front + 0.5 * rear, atol=1e-9)
    scaled = Inputs(10.0, inputs.ambient_c, 2.0 * inputs.q_front_w, 0.5 * inputs.q_rear_w)
    np.testing.assert_allclose(run(2.0, 0.5), toy_rom.simulate_sensors(h, scaled, 20.0)[0], atol=1e-9)
    full = _full(toy_fe, h[0], inputs, np.full(toy_fe.n_nodes, 20.0), scale=(2.0, 0.5))
    assert np.max(np.abs(run(2.0, 0.5) - full)) < 0.05


def test_t0_field_is_projected(toy_rom: ReducedModel, toy_fe: ToyFE) -> None:
    rng = np.random.default_rng(5)
    a = rng.normal(size=toy_rom.rank)
    np.testing.assert_allclose(toy_rom.project(toy_rom.lift(a)), a, atol=1e-9)
    h = np.full((1, 7), 60.0)
    inputs = _inputs(30)
    uniform = toy_rom.simulate_sensors(h, inputs, 23.0)
    np.testing.assert_allclose(
        toy_rom.simulate_sensors(h, inputs, np.full(toy_rom.n_nodes, 23.0)), uniform, atol=1e-9
    )
    hot = rom_train.steady_field(toy_fe, np.full(7, 15.0), ambient_c=20.0, q_front_w=250.0, q_rear_w=100.0)
    red = toy_rom.simulate_sensors(h, inputs, hot)[0]
    full = _full(toy_fe, h[0], inputs, hot)
    assert np.max(np.abs(red[0] - toy_fe.sensor_op @ hot)) < 0.02
    assert np.max(np.abs(red - full)) < 0.05


def test_mid_window_step_change(toy_rom: ReducedModel, toy_fe: ToyFE) -> None:
    h = np.array([100.0, 40.0, 70.0, 45.0, 50.0, 70.0, 15.0])
    n = 120
    qf = np.where(np.arange(n) < 60, 80.0, 260.0)
    inputs = Inputs(10.0, np.where(np.arange(n) < 90, 20.0, 23.0), qf, np.full(n, 60.0))
    red = toy_rom.simulate_sensors(h[None, :], inputs, 20.0)[0]
    full = _full(toy_fe, h, inputs, np.full(toy_fe.n_nodes, 20.0))
    assert np.max(np.abs(red - full)) < 0.05
    # the step is felt right after step 60 and not before
    rise = red[61:] - red[60]
    assert np.max(rise) > 1.0
    np.testing.assert_allclose(
        red[:61],
        toy_rom.simulate_sensors(
            h[None, :],
            inputs.__class__(10.0, inputs.ambient_c[:60], np.full(60, 80.0), inputs.q_rear_w[:60]),
            20.0,
        )[0],
        atol=1e-9,
    )


def test_steady_state_is_the_limit_and_matches_fe(toy_rom: ReducedModel, toy_fe: ToyFE) -> None:
    h = np.array([20.0, 60.0, 90.0, 10.0, 150.0, 35.0, 8.0])
    a_ss = toy_rom.steady_state(h, ambient_c=22.0, q_front_w=120.0, q_rear_w=70.0)
    long = Inputs(3600.0, np.full(200, 22.0), np.full(200, 120.0), np.full(200, 70.0))
    np.testing.assert_allclose(toy_rom.simulate_state(h, long, 22.0)[-1], a_ss, atol=1e-6)
    fe_ss = rom_train.steady_field(toy_fe, h, ambient_c=22.0, q_front_w=120.0, q_rear_w=70.0)
    assert np.max(np.abs(toy_rom.sensors @ a_ss - toy_fe.sensor_op @ fe_ss)) < 0.05


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"h": np.ones((2, 6))}, "h"),
        ({"h": -np.ones((2, 7))}, "h"),
        ({"load_scale": np.ones((3, 2))}, "load_scale"),
        ({"t0": np.ones(5)}, "t0"),
        ({"inputs": Inputs(10.0, np.ones(4), np.ones(3), np.ones(4))}, "q_front_w"),
        ({"inputs": Inputs(0.0, np.ones(4), np.ones(4), np.ones(4))}, "dt_s"),
    ],
)
def test_bad_arguments_name_the_field(toy_rom: ReducedModel, kwargs: dict, field: str) -> None:
    args = {"h": np.ones((2, 7)), "inputs": _inputs(4), "t0": 20.0, "load_scale": None} | kwargs
    with pytest.raises(RomError, match=field):
        toy_rom.simulate_sensors(args["h"], args["inputs"], args["t0"], load_scale=args["load_scale"])


def test_cache_round_trip_and_rebuild_on_key_change(tmp_path: Path, toy_fe: ToyFE, toy_spec: ToySpec) -> None:
    opts = {"rank": 12, "n_train": 4, "n_check": 2}
    first = load_or_build_rom(toy_fe, toy_spec, tmp_path, **opts)
    second = load_or_build_rom(toy_fe, toy_spec, tmp_path, **opts)
    assert not first.from_cache and second.from_cache
    assert second.key == first.key and second.error_report == first.error_report
    h = np.array([[10.0, 20.0, 30.0, 40.0, 50.0, 60.0, 70.0]])
    inputs = _inputs(20)
    np.testing.assert_array_equal(
        first.simulate_sensors(h, inputs, 20.0), second.simulate_sensors(h, inputs, 20.0)
    )
    other = load_or_build_rom(toy_fe, toy_spec, tmp_path, **(opts | {"rank": 10}))
    assert not other.from_cache and other.key != first.key and other.rank == 10
    changed_spec = load_or_build_rom(toy_fe, ToySpec(h_box=(5.0, 150.0)), tmp_path, **opts)
    assert not changed_spec.from_cache and changed_spec.h_box == (5.0, 150.0)
    assert len(list(tmp_path.glob("rom-*.npz"))) == 3


def test_corrupt_cache_is_rebuilt(tmp_path: Path, toy_fe: ToyFE, toy_spec: ToySpec) -> None:
    opts = {"rank": 8, "n_train": 2, "n_check": 1}
    first = load_or_build_rom(toy_fe, toy_spec, tmp_path, **opts)
    (path,) = tmp_path.glob("rom-*.npz")
    path.write_bytes(path.read_bytes()[:100])
    again = load_or_build_rom(toy_fe, toy_spec, tmp_path, **opts)
    assert not again.from_cache and again.key == first.key
    assert load_or_build_rom(toy_fe, toy_spec, tmp_path, **opts).from_cache
