"""The spectral split (``model.rom_split``) of the served reduced model against its exact modal evaluation."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from model import rom_modal, rom_split, rom_stream
from model.fem import FEModel, steady_state
from model.inputs import InputSeries
from model.rom import ReducedModel


@pytest.fixture(scope="module")
def fe(coarse_fe: FEModel) -> FEModel:
    return coarse_fe


@pytest.fixture(scope="module")
def rom(coarse_rom: ReducedModel) -> ReducedModel:
    return coarse_rom


def _window(n: int) -> InputSeries:
    """Heat step a third of the way in, ambient drifting every step, a second heat step near the end."""
    k = np.arange(n)
    front = np.where(k < n // 3, 80.0, 220.0) - np.where(k >= n - 5, 150.0, 0.0)
    return InputSeries(10.0, 21.8 + 2.0 * k / n, front, np.where(k < n // 3, 40.0, 120.0))


def test_split_is_the_served_evaluation_and_close_to_the_exact_one(rom: ReducedModel, fe: FEModel) -> None:
    assert rom.substeps == 0 and rom.split_active
    rng = np.random.default_rng(5)
    lo, hi = rom.h_box
    hs = lo * (hi / lo) ** rng.random((6, 7))
    t0 = steady_state(fe, np.full(7, 40.0), ambient_c=21.8, q_front_w=150.0, q_rear_w=60.0)
    scale = rng.uniform(0.6, 1.4, (6, 2))
    shift = rng.uniform(-2.0, 2.0, 6)
    inputs = _window(90)
    got = rom.simulate_sensors(hs, inputs, t0, load_scale=scale, t0_shift=shift)
    exact = replace(rom, n_slow=0).simulate_sensors(hs, inputs, t0, load_scale=scale, t0_shift=shift)
    err = np.abs(got - exact)
    assert err.max() <= 0.005, err.max()  # measured 0.002-0.003 °C on the service's mesh (docs/design/rom.md)
    assert err.max() > 1e-9  # the split is an approximation: this is not the exact path
    np.testing.assert_allclose(got[:, 0], exact[:, 0], atol=1e-9)  # the start is the exact projection
    # one candidate at a time takes the trajectory path, the population the streamed one: same numbers
    for p in (0, 3):
        alone = rom.simulate_sensors(hs[p : p + 1], inputs, t0 + shift[p], load_scale=scale[p : p + 1])[0]
        np.testing.assert_allclose(got[p], alone, atol=1e-9)


def test_split_is_off_for_theta_steps_and_for_n_slow_zero(rom: ReducedModel) -> None:
    h = np.full((2, 7), 50.0)
    inputs = _window(30)
    be = replace(rom, substeps=1)
    assert not be.split_active and not replace(rom, n_slow=0).split_active
    np.testing.assert_array_equal(
        be.simulate_sensors(h, inputs, 20.0), replace(be, n_slow=0).simulate_sensors(h, inputs, 20.0)
    )


def test_split_follows_a_steady_state(rom: ReducedModel) -> None:
    """Held inputs from the model's own steady field: nothing may move (the static condensation is exact)."""
    h = np.array([[30.0, 60.0, 45.0, 80.0, 25.0, 120.0, 15.0]])
    a = rom.steady_state(h[0], ambient_c=22.0, q_front_w=150.0, q_rear_w=70.0)
    inputs = InputSeries.constant(40, dt_s=10.0, ambient_c=22.0, q_front_w=150.0, q_rear_w=70.0)
    y = rom.simulate_sensors(h, inputs, rom.lift(a))[0]
    np.testing.assert_allclose(y, np.broadcast_to(y[0], y.shape), atol=1e-8)


def test_short_windows_and_bad_split_are_handled(rom: ReducedModel) -> None:
    h = np.full((3, 7), 40.0)
    for n in (0, 1, 3):
        inputs = _window(max(n, 1))
        if n == 0:
            inputs = InputSeries(10.0, np.zeros(0), np.zeros(0), np.zeros(0))
        got = rom.simulate_sensors(h, inputs, 21.0)
        exact = replace(rom, n_slow=0).simulate_sensors(h, inputs, 21.0)
        assert got.shape == exact.shape == (3, n + 1, 32)
        assert np.abs(got - exact).max() <= 0.005
    with pytest.raises(ValueError, match="n_slow"):
        ops = (rom.k0, rom.k_zone, rom.z_zone, rom.q_front, rom.q_rear, rom.sensors)
        rom_split.split_operators(*ops, h_centre=h[0], n_slow=rom.rank)


def test_auto_split_is_the_first_gap() -> None:
    lam = np.array([0.001, 0.002, 0.05, 0.08, 0.10, 0.11, 0.16, 0.30, 0.33, 0.5])
    assert rom_split.choose_split(lam) == 6  # 0.16 ≥ 1.15·0.11 and ≥ 0.12 /s; 0.10 / 0.08 is below the floor
    assert rom_split.choose_split(np.linspace(0.1, 0.2, 10)) == 0  # no gap: all-exact


def test_lagged_inputs_rows() -> None:
    u = np.arange(15.0).reshape(5, 3) ** 2
    rows = rom_split.lagged_inputs(u, 2)
    du = np.vstack([np.zeros(3), np.diff(u, axis=0)])
    np.testing.assert_array_equal(rows[:, :3], u)
    np.testing.assert_array_equal(rows[:, 3:6], du)  # row n: Δu(n), Δu(0) := 0
    np.testing.assert_array_equal(rows[:, 6:9], np.vstack([np.zeros((2, 3)), du[1:4]]))  # Δu(n−1), n−1 ≥ 1


def test_streamed_direct_term_is_rows_times_weights() -> None:
    rng = np.random.default_rng(2)
    p, r, m, n = 5, 30, 4, 70
    lam = rng.uniform(0.001, 0.3, (p, r))
    mu, _ = rom_modal.step_factors(lam, 10.0, 1.0, 0)
    forcing = (rng.normal(size=(p, r)), rng.normal(size=(p, r)), rng.normal(size=(p, r)))
    seg = rom_modal.split_segments(rng.normal(size=n), np.repeat(rng.normal(size=7), 10), np.ones(n))
    run = rom_modal.ModalRun(rng.normal(size=(p, r)), lam, mu, forcing, seg, np.ones((p, 2)))
    gain = rng.normal(size=(p, m, r))
    rows, weights = rng.normal(size=(n, 6)), rng.normal(size=(p, 6, m))
    plain = rom_stream.modal_outputs(run, gain, chunk=16)
    got = rom_stream.modal_outputs(run, gain, chunk=16, direct=(rows, weights))
    np.testing.assert_allclose(got[:, 0], plain[:, 0], atol=1e-12)
    np.testing.assert_allclose(got[:, 1:], plain[:, 1:] + rows[None] @ weights, atol=1e-10)


def test_split_falls_back_to_exact_where_its_guards_fail(rom: ReducedModel) -> None:
    """Short steps (the fast modes would outlive the kept transient steps) use the all-exact evaluation."""
    ops = rom._split_operators
    assert ops is not None and ops.usable(10.0)
    assert ops.centre_lam is not None
    fast = float(ops.centre_lam[ops.n_slow])
    dt = 0.5 * rom_split.MIN_FAST_DECAY / fast
    assert not ops.usable(dt)
    k = np.arange(20)
    inputs = InputSeries(dt, 21.0 + 0.1 * k, np.where(k < 8, 50.0, 150.0), np.full(20, 30.0))
    h = np.full((2, 7), 60.0)
    np.testing.assert_array_equal(
        rom.simulate_sensors(h, inputs, 21.0), replace(rom, n_slow=0).simulate_sensors(h, inputs, 21.0)
    )
