"""The robustness bench's regression peers (``benchmarks.robustness.peers``) on known linear systems."""

from __future__ import annotations

import numpy as np
import pytest

from benchmarks.robustness import peers as P


def _walk(n: int, p: int, seed: int = 0) -> np.ndarray:
    """Smooth, correlated inputs like temperatures (random walks)."""
    return np.cumsum(np.random.default_rng(seed).normal(size=(n, p)), axis=0) * 0.1


def _raw(peer: P.LinearPeer) -> np.ndarray:
    """The coefficients on the unstandardised inputs, per lag."""
    return (peer.coef / peer.scale).reshape(peer.lags + 1, -1)


W = np.array([1.0, -2.0, 0.0, 0.0, 0.5, 0.0])


def test_ridge_and_lasso_recover_a_static_linear_system() -> None:
    x = _walk(2000, 6)
    y = x @ W + 3.0 + np.random.default_rng(1).normal(0.0, 0.05, 2000)
    rows = np.arange(0, 2000, 5)
    for fit in (P.fit_ridge, P.fit_lasso):
        peer = fit(x, y[rows], rows)
        np.testing.assert_allclose(_raw(peer)[0], W, atol=0.02)
        pred = peer.predict_rows(x, rows)
        assert np.sqrt(np.mean((pred - y[rows]) ** 2)) < 0.06


def test_lasso_drops_inputs_that_do_not_matter_when_the_data_are_noisy() -> None:
    x = _walk(2000, 6, seed=2)
    y = x @ W + np.random.default_rng(3).normal(0.0, 0.5, 2000)
    rows = np.arange(0, 2000, 5)
    peer = P.fit_lasso(x, y[rows], rows)
    assert peer.alpha > 0.0
    raw = _raw(peer)[0]
    assert np.all(np.abs(raw[[2, 3, 5]]) < 0.15)
    np.testing.assert_allclose(raw[[0, 1, 4]], W[[0, 1, 4]], atol=0.2)


def test_cross_validation_penalises_more_when_the_signal_is_pure_noise() -> None:
    x = _walk(1200, 20, seed=4)
    rows = np.arange(0, 1200, 4)
    noise = np.random.default_rng(5).normal(0.0, 1.0, 1200)
    signal = x[:, :3] @ np.array([1.0, -1.0, 0.5])
    clean = P.fit_ridge(x, (signal + 0.01 * noise)[rows], rows)
    pure = P.fit_ridge(x, noise[rows], rows)
    assert pure.alpha > 100.0 * clean.alpha
    assert np.abs(pure.predict_rows(x, rows)).max() < 1.0  # shrunk towards the mean, not fitted to noise


def test_arx_finds_the_lag_of_a_delayed_input() -> None:
    x = _walk(2000, 4, seed=6)
    lag_rows = 10
    delayed = np.vstack([np.repeat(x[:1], 2 * lag_rows, axis=0), x[: -2 * lag_rows]])
    y = x[:, 0] + 2.0 * delayed[:, 1] + 1.0
    rows = np.arange(0, 2000, 5)
    peer = P.fit_arx(x, y[rows], rows, lag_rows=lag_rows)
    assert peer.lags >= 2
    raw = _raw(peer)
    assert raw[0, 0] == pytest.approx(1.0, abs=0.05)
    assert raw[2, 1] == pytest.approx(2.0, abs=0.05)
    static = P.fit_ridge(x, y[rows], rows)
    assert peer.cv_mse < 0.1 * static.cv_mse


def test_blocked_folds_are_contiguous_and_cover_every_row() -> None:
    folds = P.blocked_folds(23, 5)
    assert np.array_equal(np.concatenate(folds), np.arange(23))
    assert all(np.all(np.diff(f) == 1) for f in folds)
    with pytest.raises(P.PeerError, match="folds"):
        P.blocked_folds(5, 5)


def test_hold_flagged_keeps_the_last_good_reading() -> None:
    t = np.array([[1.0, 5.0], [2.0, -327.68], [3.0, -327.68], [4.0, 7.0]])
    status = np.array([[0, 0], [0, 1], [0, 1], [0, 0]])
    np.testing.assert_array_equal(P.hold_flagged(t, status), [[1, 5], [2, 5], [3, 5], [4, 7]])
    first_bad = P.hold_flagged(np.array([[-327.68], [6.0]]), np.array([[1], [0]]))
    np.testing.assert_array_equal(first_bad, [[6.0], [6.0]])
