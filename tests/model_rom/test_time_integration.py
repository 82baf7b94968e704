"""The reduced model's time integration over one held input step (``rom_modal.step_factors``)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from model import rom_modal
from model.inputs import InputSeries
from model.rom import ReducedModel


def test_exact_step_is_the_limit_of_theta_substeps() -> None:
    lam = np.array([[1e-4, 3e-3, 0.05, 2.0]])
    exact, gamma = rom_modal.step_factors(lam, 10.0, 1.0, 0)
    np.testing.assert_allclose(exact, np.exp(-10.0 * lam), rtol=1e-14)
    np.testing.assert_allclose(gamma, (1.0 - exact) / lam, rtol=1e-14)
    fine, _ = rom_modal.step_factors(lam, 10.0, 1.0, 100_000)
    np.testing.assert_allclose(fine, exact, atol=1e-5)
    one, g1 = rom_modal.step_factors(lam, 10.0, 1.0, 1)
    np.testing.assert_allclose(one, 1.0 / (1.0 + 10.0 * lam), rtol=1e-14)
    np.testing.assert_allclose(g1, 1.0 / (0.1 + lam), rtol=1e-12)  # (1 − μ)/λ loses a few digits


def test_exact_rom_equals_its_own_matrix_exponential(toy_rom: ReducedModel) -> None:
    """Substeps 0 solves the reduced ODE exactly for held inputs: compare with scipy's expm of the same
    reduced system over two held steps."""
    from scipy.linalg import expm

    rom = replace(toy_rom, substeps=0)
    h = np.array([30.0, 60.0, 20.0, 90.0, 40.0, 70.0, 15.0])
    inputs = InputSeries(10.0, np.array([20.0, 25.0]), np.array([50.0, 0.0]), np.array([0.0, 30.0]))
    a = rom.simulate_state(h, inputs, 18.0)
    kr = rom_modal.conductance(rom.k0, rom.k_zone, h[None, :])[0]
    x = rom.initial_state(18.0)
    for n in range(2):
        z = (
            inputs.ambient_c[n] * (h @ rom.z_zone)
            + inputs.q_front_w[n] * rom.q_front
            + inputs.q_rear_w[n] * rom.q_rear
        )
        star = np.linalg.solve(kr, z)
        x = star + expm(-10.0 * kr) @ (x - star)
        np.testing.assert_allclose(a[n + 1], x, atol=1e-9)
