"""The H-map families (model.hmap): Jacobians, bands, priors, model-form error against the plant's truth."""

from __future__ import annotations

import numpy as np
import pytest

from model import hmap
from model.geometry import load_spindle
from model.hmap import NODES, PHYSICS, Family, Gaussian, HMapError
from model.plant import h_true

FAMILIES = [PHYSICS, NODES]
SPEEDS = np.array([0.0, 250.0, 1000.0, 3333.0, 6999.0, 7500.0])


@pytest.fixture(scope="module")
def spec():  # type: ignore[no-untyped-def]
    return load_spindle()


@pytest.mark.parametrize("family", FAMILIES, ids=lambda f: f.kind)
def test_jacobian_matches_finite_differences(family: Family, spec) -> None:  # type: ignore[no-untyped-def]
    theta = family.prior(spec).mean + np.random.default_rng(0).normal(0, 0.2, family.n_theta)
    amb = np.linspace(19.0, 25.0, SPEEDS.size)
    jac = family.log_h_jacobian(theta, SPEEDS, amb)
    eps = 1e-6
    fd = np.stack(
        [
            (family.log_h(theta + eps * e, SPEEDS, amb) - family.log_h(theta - eps * e, SPEEDS, amb))
            / (2 * eps)
            for e in np.eye(family.n_theta)
        ],
        axis=-1,
    )
    np.testing.assert_allclose(jac, fd, atol=1e-7)
    e0 = np.eye(family.n_theta)[0]
    fd_h = (family.h_at(theta + eps * e0, SPEEDS, amb) - family.h_at(theta - eps * e0, SPEEDS, amb)) / (
        2 * eps
    )
    np.testing.assert_allclose(family.h_jacobian(theta, SPEEDS, amb)[:, :, 0], fd_h, rtol=1e-6, atol=1e-7)


@pytest.mark.parametrize("family", FAMILIES, ids=lambda f: f.kind)
def test_shapes_population_and_positive_band(family: Family, spec) -> None:  # type: ignore[no-untyped-def]
    prior = family.prior(spec)
    h = family.h_at(prior.mean, SPEEDS, 22.0)
    assert h.shape == (SPEEDS.size, 7) and np.all(h > 0)
    levels = np.ones(family.n_theta) if family.kind == "nodes" else (np.arange(family.n_theta) % 3 != 2)
    pop = family.h_at(np.stack([prior.mean, prior.mean + 0.1 * levels]), SPEEDS, 22.0)
    assert pop.shape == (2, SPEEDS.size, 7)
    np.testing.assert_allclose(pop[0], h)
    np.testing.assert_allclose(pop[1], h * np.exp(0.1), rtol=1e-12)  # all levels +0.1: ln H + 0.1
    mid, lo, hi = family.h_ci95_at(prior.mean, prior.cov, SPEEDS, 22.0)
    assert np.all(lo > 0) and np.all(lo < mid) and np.all(mid < hi)
    np.testing.assert_allclose(np.log(hi / mid), np.log(mid / lo))  # symmetric in ln H


def test_nodes_interpolate_linearly_in_log_h_and_hold_outside() -> None:
    theta = np.tile(np.log(np.arange(1.0, 9.0) * 10.0), 7)
    h = NODES.h_at(theta, [1000.0, 1500.0, 7000.0, 9000.0], hmap.T_REF_C)
    np.testing.assert_allclose(h[:, 0], [20.0, np.sqrt(20.0 * 30.0), 80.0, 80.0])


@pytest.mark.parametrize("family", FAMILIES, ids=lambda f: f.kind)
def test_family_does_not_contain_the_plant_truth(family: Family) -> None:
    """The best fit over 0..7000 rpm leaves an error (measured values in docs/design/hmap.md)."""
    _, worst, rms = family.form_error(h_true)
    assert np.all(worst > 5e-4)
    assert worst.max() < (0.2 if family.kind == "physics" else 0.03)
    assert np.all(rms <= worst)


def test_physics_prior_follows_the_empirical_correlations(spec) -> None:  # type: ignore[no-untyped-def]
    from model.empirical import empirical_h

    prior = PHYSICS.prior(spec)
    for n in (1000.0, 3000.0, 5000.0):
        h = PHYSICS.h_at(prior.mean, n)[0]
        emp = empirical_h(spec, n, hmap.T_REF_C)
        np.testing.assert_allclose(h[1:5], emp[1:5], rtol=0.1)  # H2-H5: laminar, one regime
        assert h[6] == pytest.approx(emp[6], rel=0.02)  # H7: natural convection, speed-independent


def test_ambient_dependence_is_the_air_properties_only() -> None:
    theta = np.zeros(NODES.n_theta)
    h20, h30 = NODES.h_at(theta, 3000.0, 20.0)[0], NODES.h_at(theta, 3000.0, 30.0)[0]
    per_k = (h30 / h20 - 1.0) / 10.0
    assert np.all(np.abs(per_k) < 3e-3)  # well below 0.3 %/K
    assert per_k[6] > 0  # stationary: the conductivity only


def test_becker_kaye_regimes() -> None:
    # Ta below 1700: conduction across the gap, Nu = 2 at 2δ
    h = hmap.becker_kaye_h(np.array([0.0, 1.0, 5000.0]), r_in_m=0.04, r_out_m=0.065)
    assert h[0] == h[1]
    assert h[2] > 10 * h[0]


def test_errors_name_the_argument() -> None:
    with pytest.raises(HMapError, match="theta"):
        NODES.h_at(np.zeros(5), 1000.0)
    with pytest.raises(HMapError, match="speed_rpm"):
        NODES.h_at(np.zeros(NODES.n_theta), [[1.0]])
    with pytest.raises(HMapError, match="ambient_c"):
        NODES.h_at(np.zeros(NODES.n_theta), [1.0, 2.0], [20.0, 21.0, 22.0])
    with pytest.raises(HMapError, match="cov"):
        NODES.h_ci95_at(np.zeros(NODES.n_theta), np.eye(3), 1000.0)
    with pytest.raises(HMapError, match="cov"):
        Gaussian(np.zeros(2), np.array([[1.0, 0.0], [0.0, -1.0]]))
    with pytest.raises(HMapError, match="kind"):
        Family("table")  # type: ignore[arg-type]
    with pytest.raises(HMapError, match="nodes_rpm"):
        Family("nodes", (0.0, 2000.0, 1000.0))
