"""The MLR peer (benchmarks.studies.mlr) on synthetic data."""

from __future__ import annotations

import numpy as np
import pytest

from benchmarks.studies.mlr import MlrError, fit_mlr, select_sensors


def _groups(rng: np.random.Generator, n: int = 400) -> tuple[np.ndarray, list[list[int]]]:
    """12 sensors in 4 groups of 3, each group a noisy copy of its own independent signal."""
    t = np.linspace(0.0, 1.0, n)
    base = [np.sin(2 * np.pi * f * t + p) for f, p in ((1, 0.0), (2.3, 1.0), (3.7, 2.0), (5.1, 0.5))]
    cols, groups = [], []
    for b in base:
        groups.append([])
        for _ in range(3):
            groups[-1].append(len(cols))
            cols.append(20.0 + 5.0 * b + rng.normal(0.0, 0.05, n))
    return np.column_stack(cols), groups


def test_one_sensor_per_cluster() -> None:
    rng = np.random.default_rng(1)
    temps, groups = _groups(rng)
    disp = 2.0 * temps[:, 4] - 1.0 * temps[:, 9] + rng.normal(0.0, 0.01, temps.shape[0])
    picks, clusters = select_sensors(temps, disp, n_clusters=4)
    assert sorted(sorted(c) for c in clusters) == sorted(groups)
    assert len(picks) == 4
    assert sorted(next(i for i, g in enumerate(groups) if p in g) for p in picks) == [0, 1, 2, 3]
    assert 4 in picks and 9 in picks  # the driving sensors are their clusters' best


def test_recovers_planted_linear_model() -> None:
    rng = np.random.default_rng(2)
    n = 300
    temps = 20.0 + rng.normal(0.0, 2.0, (n, 8))  # independent sensors: each its own cluster
    coef = np.array([1.5, -0.7, 0.3, 2.0])
    chosen = [0, 3, 5, 7]
    disp = 4.0 + temps[:, chosen] @ coef + rng.normal(0.0, 0.01, n)
    disp[::17] = np.nan  # missing readings are skipped
    m = fit_mlr(temps, disp, n_clusters=8)
    full = dict(zip(m.sensors, m.coef, strict=True))
    np.testing.assert_allclose([full[c] for c in chosen], coef, atol=0.01)
    np.testing.assert_allclose([full[c] for c in (1, 2, 4, 6)], 0.0, atol=0.01)
    assert m.intercept == pytest.approx(4.0, abs=0.3)
    assert m.residual_rms_um < 0.02
    fresh = 20.0 + rng.normal(0.0, 2.0, (50, 8))
    np.testing.assert_allclose(m.predict(fresh), 4.0 + fresh[:, chosen] @ coef, atol=0.1)


def test_bad_input() -> None:
    with pytest.raises(MlrError):
        fit_mlr(np.zeros((10, 4)), np.zeros(9))
    with pytest.raises(MlrError):
        select_sensors(np.ones((50, 4)), np.arange(50.0), n_clusters=2)  # all constant
