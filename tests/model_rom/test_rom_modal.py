"""The modal closed form: both evaluation paths (per-segment loop, log-depth scan) against a plain loop."""

from __future__ import annotations

import numpy as np
import pytest

from model import rom_modal


def _plain(b0: np.ndarray, mu: np.ndarray, increments: np.ndarray) -> np.ndarray:
    out = [b0]
    for d in increments:
        out.append(mu * out[-1] + d)
    return np.array(out)


@pytest.mark.parametrize("method", ["loop", "scan", "blocked", "auto"])
@pytest.mark.parametrize("theta", [1.0, 0.5])
def test_segment_loop_and_scan_agree_with_plain_recursion(theta: float, method: str) -> None:
    rng = np.random.default_rng(0)
    p, r, n = 3, 5, 50
    lam = rng.uniform(1e-3, 50.0, (p, r))  # up to λ·Δt = 500: μ < 0 for Crank–Nicolson
    mu, gamma = rom_modal.step_factors(lam, 10.0, theta)
    amb = np.repeat(rng.uniform(15, 30, 5), 10)
    qf = np.r_[np.full(25, 100.0), np.full(25, 200.0)]
    qr = rng.uniform(0, 50, n)  # changes every step
    forcing = tuple(rng.normal(size=(p, r)) for _ in range(3))
    scale = rng.uniform(0.5, 1.5, (p, 2))
    b0 = rng.normal(size=(p, r))
    c = (
        amb[:, None, None] * forcing[0]
        + qf[:, None, None] * forcing[1] * scale[:, 0:1]
        + qr[:, None, None] * forcing[2] * scale[:, 1:2]
    )
    expected = _plain(b0, mu, gamma * c)
    seg = rom_modal.split_segments(amb, qf, qr)
    assert seg.start.size == n  # qr makes every step its own segment
    got = rom_modal.modal_trajectory(rom_modal.ModalRun(b0, lam, mu, forcing, seg, scale), method=method)
    np.testing.assert_allclose(got, expected, atol=1e-9)
    scan = np.empty_like(expected)
    scan[0] = b0
    scan[1:] = gamma * c
    np.testing.assert_allclose(rom_modal.linear_scan(scan, mu), expected, atol=1e-9)
    few = rom_modal.split_segments(amb, qf, np.zeros(n))
    assert few.start.size == 6
    c_few = amb[:, None, None] * forcing[0] + qf[:, None, None] * forcing[1] * scale[:, 0:1]
    np.testing.assert_allclose(
        rom_modal.modal_trajectory(rom_modal.ModalRun(b0, lam, mu, forcing, few, scale), method=method),
        _plain(b0, mu, gamma * c_few),
        atol=1e-9,
    )


def test_method_choice() -> None:
    assert rom_modal.choose_method(360, 360, 50) == "blocked"
    assert rom_modal.choose_method(360, 360, 28 * 50) == "loop"
    assert rom_modal.choose_method(3, 360, 28 * 50) == "loop"
    assert rom_modal.choose_method(3, 360, 50) == "loop"


@pytest.mark.parametrize("n", [1, 2, 7, 16, 17, 361])
def test_blocked_recursion_matches_scan_for_any_length(n: int) -> None:
    rng = np.random.default_rng(n)
    mu = rng.uniform(-0.9, 0.999, (2, 3))
    y = rng.normal(size=(n + 1, 2, 3))
    np.testing.assert_allclose(
        rom_modal.blocked_recursion(y.copy(), mu), rom_modal.linear_scan(y.copy(), mu), atol=1e-9
    )
