"""The filter's algebra on the service's reduced model: open loop without data, textbook update, masks,
offsets, the considered parameter errors against Monte Carlo, prior, field σ, NIS window, errors."""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np
import pytest
from scipy.stats import chi2

from model.estimator import (
    N_PARAMS,
    CovarianceError,
    Estimate,
    EstimatorError,
    NisWindow,
    NoiseModel,
    StateEstimator,
    StepInput,
    check_covariance,
    convergence,
    field_std,
    heated_prior,
    param_jacobian,
    predict_mean,
    rescale_cross,
    transition,
    uniform_state,
    wide_prior,
)
from model.estimator_noise import DefectCase, rom_defect_cov
from model.inputs import InputSeries
from model.rom import DEFAULT_SUBSTEPS

H = np.array([88.21, 46.32, 68.49, 46.72, 52.13, 70.23, 16.54])


def _inputs(n: int = 120) -> InputSeries:
    k = np.arange(n)
    return InputSeries(
        10.0,
        22.0 + 0.01 * k,
        np.where(k < 40, 0.0, np.where(k < 80, 150.0, 90.0)),
        np.where(k < 40, 0.0, 70.0),
    )


def _step(inputs: InputSeries, k: int, h: np.ndarray = H) -> StepInput:
    return StepInput(h, float(inputs.ambient_c[k]), float(inputs.q_front_w[k]), float(inputs.q_rear_w[k]))


def _hot_start(rom: Any) -> np.ndarray:
    """A non-uniform field (N,) [°C]: a steady state of another H and load."""
    a = rom.steady_state(H * 0.6, ambient_c=21.0, q_front_w=200.0, q_rear_w=100.0)
    return np.asarray(rom.lift(a))


def _filter(rom: Any, start: np.ndarray, **kw: Any) -> StateEstimator:
    prior = wide_prior(rom, ambient_c=22.0)
    return StateEstimator(rom, Estimate(rom.initial_state(start), prior.cov, prior.cross), **kw)


def test_without_measurements_the_mean_is_the_open_loop_reduced_model(model: Any) -> None:
    rom, inputs = model.rom, _inputs()
    assert rom.substeps == DEFAULT_SUBSTEPS  # the served model's step (exact over each held step)
    start = _hot_start(rom)
    est = _filter(rom, start)
    states = rom.simulate_state(H, inputs, start)
    # the filter steps the whole reduced state exactly: compare with the all-exact evaluation (n_slow 0); the
    # served one (spectral split, model.rom_split) is within a few mK of it
    sensors = replace(rom, n_slow=0).simulate_sensors(H[None, :], inputs, start)[0]
    served = rom.simulate_sensors(H[None, :], inputs, start)[0]
    assert np.abs(served - sensors).max() <= 0.005
    garbage = np.full(32, 1e3)
    for k in range(inputs.n_steps):
        # every channel masked out, or every value missing: no update at all
        res = est.step(
            _step(inputs, k), garbage if k % 2 else np.full(32, np.nan), np.zeros(32, bool) if k % 2 else None
        )
        assert res.dof == 0 and res.nis == 0.0 and np.all(np.isnan(res.innovation))
        np.testing.assert_allclose(est.estimate.mean, states[k + 1], rtol=0, atol=1e-9 * np.abs(states).max())
        np.testing.assert_allclose(est.sensors_mean(), sensors[k + 1], rtol=0, atol=1e-9)
    np.testing.assert_allclose(est.field_mean(), rom.lift(states[-1]), rtol=0, atol=1e-9)
    np.testing.assert_allclose(est.field_mean([5, 500]), rom.lift(states[-1])[[5, 500]], rtol=0, atol=1e-9)


@pytest.mark.parametrize("substeps", [0, 1, 4])
def test_parameter_jacobian_is_the_derivative_of_the_step(model: Any, substeps: int) -> None:
    """∂a⁺/∂p against central differences of the step with H_i·(1 ± ε) and Q·(1 ± ε), from a hot field."""
    rom = replace(model.rom, substeps=substeps)
    a0 = rom.initial_state(_hot_start(rom))
    u = StepInput(H, 22.5, 180.0, 90.0)
    jac = param_jacobian(rom, transition(rom, H, 10.0), u, a0)
    eps = 1e-4  # the reduced coordinates are ~1e4 (√heat capacity): a smaller step loses digits
    for i in range(N_PARAMS):
        scale = np.ones(N_PARAMS)
        cols = []
        for sign in (1.0, -1.0):
            scale[i] = 1.0 + sign * eps
            ui = StepInput(H * scale[:7], u.ambient_c, u.q_front_w * scale[7], u.q_rear_w * scale[8])
            cols.append(predict_mean(transition(rom, ui.h, 10.0), a0, ui))
        fd = (cols[0] - cols[1]) / (2 * eps)
        assert np.abs(fd).max() > 1e-3
        np.testing.assert_allclose(jac[:, i], fd, rtol=0, atol=1e-6 * np.abs(fd).max())


def _textbook_update(sensors: np.ndarray, est: Estimate, y: np.ndarray, use: np.ndarray, r_var: float) -> Any:
    c = sensors[use]
    s = c @ est.cov @ c.T + r_var * np.eye(c.shape[0])
    k = est.cov @ c.T @ np.linalg.inv(s)
    nu = y[use] - c @ est.mean
    return est.mean + k @ nu, est.cov - k @ s @ k.T, float(nu @ np.linalg.inv(s) @ nu)


def test_update_is_the_kalman_update_over_the_usable_channels_only(model: Any) -> None:
    rom, inputs = model.rom, _inputs()
    est = _filter(rom, _hot_start(rom))
    for k in range(5):
        est.predict(_step(inputs, k))
    prior = est.estimate
    rng = np.random.default_rng(1)
    y = est.sensors_mean() + rng.normal(0.0, 0.3, 32)
    mask = np.ones(32, bool)
    mask[[3, 7, 20]] = False
    res = est.update(y, mask)
    mean, cov, nis = _textbook_update(np.asarray(rom.sensors), prior, y, mask, est.noise.r_var)
    np.testing.assert_allclose(res.estimate.mean, mean, rtol=0, atol=1e-9)
    np.testing.assert_allclose(res.estimate.cov, cov, rtol=0, atol=1e-9 * np.abs(cov).max())
    assert res.nis == pytest.approx(nis, rel=1e-9) and res.dof == 29
    assert np.all(np.isnan(res.innovation[~mask])) and np.all(np.isfinite(res.innovation[mask]))
    # masked channels' values do not matter at all; a NaN on a channel in the mask equals masking it
    for bad in (np.full(32, 1e6), np.full(32, np.nan)):
        y2 = np.where(mask, y, bad)
        other = StateEstimator(rom, prior, noise=est.noise).update(y2, mask if bad[0] > 0 else None)
        np.testing.assert_array_equal(other.estimate.mean, res.estimate.mean)
        np.testing.assert_array_equal(other.estimate.cov, res.estimate.cov)
        assert other.nis == res.nis


def test_offsets_are_subtracted_before_the_update(model: Any) -> None:
    rom = model.rom
    prior = wide_prior(rom, ambient_c=22.0)
    offsets = np.linspace(-0.3, 0.3, 32)
    y = np.full(32, 24.0)
    with_offsets = StateEstimator(rom, prior, offsets_c=offsets).update(y + offsets)
    without = StateEstimator(rom, prior).update(y)
    np.testing.assert_allclose(with_offsets.estimate.mean, without.estimate.mean, rtol=0, atol=1e-12)


def test_considered_parameter_errors_match_monte_carlo(model: Any) -> None:
    """No data, zero start covariance, constant relative errors of H and loads (τ = ∞): the filter's sensor σ
    after an hour equals the spread of reduced runs with sampled H and load errors (linearisation holds at
    5 %; 2000 samples: sampling error of a σ ~1.6 %)."""
    rom, inputs = model.rom, _inputs(360)
    start = _hot_start(rom)
    noise = NoiseModel(h_rel=0.05, load_rel=0.05, param_tau_s=np.inf)
    r = rom.rank
    est = StateEstimator(
        rom, Estimate(rom.initial_state(start), np.zeros((r, r)), np.zeros((r, N_PARAMS))), noise=noise
    )
    for k in range(inputs.n_steps):
        est.predict(_step(inputs, k))
    rng = np.random.default_rng(7)
    p = 0.05 * rng.standard_normal((2000, N_PARAMS))
    runs = rom.simulate_sensors(H[None, :] * (1.0 + p[:, :7]), inputs, start, load_scale=1.0 + p[:, 7:])
    mc_std = runs[:, -1, :].std(axis=0)
    assert mc_std.max() > 0.05  # the errors matter: tenths of a degree at the bearings
    np.testing.assert_allclose(est.sensors_std(), mc_std, rtol=0.06)


def _joint_min_eig(est: Estimate, std: np.ndarray) -> float:
    """Smallest eigenvalue of [[P, X], [Xᵀ, Σ]] over P's largest variance."""
    joint = np.block([[est.cov, est.cross], [est.cross.T, np.diag(std**2)]])
    return float(np.linalg.eigvalsh(joint)[0] / np.diagonal(est.cov).max())


def test_a_narrower_parameter_sigma_rescales_the_cross_covariance(model: Any) -> None:
    """Heating with the considered H errors at 100 %, then 5 % (a new H with a narrow CI): ``set_noise``
    rescales the cross-covariance, the joint covariance and every predicted P stay positive semi-definite.
    Assigning the new noise without it (the old ``FilteredState.set_h``) leaves an indefinite joint and, a
    few steps later, an indefinite P: the bug of the simulated thermal test (docs/design/estimator.md)."""
    rom, inputs = model.rom, _inputs(120)
    wide, narrow = NoiseModel(h_rel=1.0), NoiseModel(h_rel=0.05)
    est = _filter(rom, _hot_start(rom), noise=wide)
    for k in range(60):
        est.predict(_step(inputs, k))
        est.update(est.sensors_mean())
    assert _joint_min_eig(est.estimate, wide.param_std()) > -1e-9
    before = est.estimate
    stale = StateEstimator(rom, before, noise=narrow)  # the old assignment: the cross kept as it was
    assert _joint_min_eig(stale.estimate, narrow.param_std()) < -1e-5
    with pytest.raises(CovarianceError, match=r"positive semi-definite|negative variance"):
        for k in range(60, 120):
            stale.predict(_step(inputs, k))
    est.set_noise(narrow)
    np.testing.assert_array_equal(est.estimate.cov, before.cov)
    np.testing.assert_allclose(est.estimate.cross[:, :7], 0.05 * before.cross[:, :7])
    np.testing.assert_array_equal(est.estimate.cross[:, 7:], before.cross[:, 7:])  # load_rel unchanged
    assert _joint_min_eig(est.estimate, narrow.param_std()) > -1e-9
    for k in range(60, 120):
        est.predict(_step(inputs, k))
        assert float(np.linalg.eigvalsh(est.estimate.cov)[0]) > -1e-9 * est.estimate.cov.diagonal().max()
    same = rescale_cross(est.estimate, narrow.param_std(), narrow.param_std())
    assert same is est.estimate  # nothing changes when the 1σ do not


def test_a_belief_that_is_no_distribution_raises_and_is_kept_out(model: Any) -> None:
    """``check_covariance`` names a non-finite value, a negative variance, an indefinite covariance; the
    filter raises ``CovarianceError`` and keeps its previous belief; round-off below 0 passes."""
    rom = model.rom
    prior = wide_prior(rom, ambient_c=22.0)
    check_covariance(prior)
    lam, phi = np.linalg.eigh(prior.cov)
    roundoff = Estimate(prior.mean, (phi * np.r_[-1e-14 * lam[-1], lam[1:]]) @ phi.T, prior.cross)
    check_covariance(roundoff)
    bad_diag = prior.cov.copy()
    bad_diag[2, 2] = -1.0
    indefinite = prior.cov.copy()  # every variance > 0, but a correlation of 2 between two coordinates
    indefinite[0, 1] = indefinite[1, 0] = 2.0 * np.sqrt(indefinite[0, 0] * indefinite[1, 1])
    nan_cov = prior.cov.copy()
    nan_cov[1, 1] = np.nan
    cases = ((bad_diag, "negative variance"), (indefinite, "positive semi-definite"), (nan_cov, "non-finite"))
    for cov, match in cases:
        with pytest.raises(CovarianceError, match=match):
            check_covariance(Estimate(prior.mean, cov, prior.cross))
    est = StateEstimator(rom, prior)
    est.estimate = Estimate(prior.mean, indefinite, prior.cross)
    with pytest.raises(CovarianceError, match=r"positive semi-definite|negative variance"):
        est.predict(_step(_inputs(2), 0))
    assert est.estimate.cov is indefinite  # not replaced by the bad prediction
    est.estimate = Estimate(prior.mean, nan_cov, prior.cross)
    with pytest.raises(CovarianceError, match="non-finite"):
        est.update(est.sensors_mean() + 0.1)
    assert est.estimate.cov is nan_cov  # nor by the bad posterior
    assert issubclass(CovarianceError, EstimatorError)


def test_wide_prior_is_uniform_at_ambient_with_the_requested_spread(model: Any) -> None:
    rom = model.rom
    prior = wide_prior(rom, ambient_c=21.5, sigma_uniform_c=4.0, sigma_shape_c=3.0)
    np.testing.assert_allclose(rom.lift(prior.mean), 21.5, rtol=0, atol=1e-9)
    sens_var = field_std(np.asarray(rom.sensors), prior.cov) ** 2
    assert sens_var.mean() == pytest.approx(4.0**2 + 3.0**2, rel=1e-9)
    u = uniform_state(rom)
    np.testing.assert_allclose(rom.lift(u), 1.0, rtol=0, atol=1e-9)


def test_heated_prior_holds_the_heated_steady_fields(model: Any) -> None:
    """Mean uniform at the ambient; a steady heated field of an H and load inside the draw's ranges lies
    within its 3σ ellipsoid (Mahalanobis distance² ≤ χ²(r) 99.9 %), far outside the isotropic prior's
    sensor-scaled shape part at the same uniform spread."""
    rom = model.rom
    prior = heated_prior(rom, ambient_c=21.0)
    np.testing.assert_allclose(rom.lift(prior.mean), 21.0, rtol=0, atol=1e-9)
    np.testing.assert_allclose(prior.cov, prior.cov.T)
    rise = rom.steady_state(H, ambient_c=0.0, q_front_w=150.0, q_rear_w=70.0)
    d2 = float(rise @ np.linalg.solve(prior.cov, rise))
    assert d2 <= chi2.ppf(0.999, rom.rank), d2
    narrow = wide_prior(rom, ambient_c=21.0, sigma_shape_c=0.1)
    assert float(rise @ np.linalg.solve(narrow.cov, rise)) > 100.0 * d2


def test_field_std_is_the_diagonal_of_the_lifted_covariance(model: Any) -> None:
    rom = model.rom
    est = _filter(rom, _hot_start(rom))
    nodes = np.random.default_rng(3).choice(rom.n_nodes, 40, replace=False)
    basis = rom.basis[nodes]
    dense = np.sqrt(np.diag(basis @ est.estimate.cov @ basis.T))
    np.testing.assert_allclose(est.field_std(nodes), dense, rtol=1e-10)
    np.testing.assert_allclose(est.field_std()[nodes], dense, rtol=1e-10)


def test_nis_window_accepts_chi_square_and_rejects_a_doubled_variance() -> None:
    rng = np.random.default_rng(0)
    good, bad = NisWindow(60, alpha=0.01), NisWindow(60, alpha=0.01)
    for _ in range(59):
        good.push(float(chi2.rvs(32, random_state=rng)), 32)
        bad.push(2.0 * float(chi2.rvs(32, random_state=rng)), 32)
    assert not good.consistent() and not good.full  # not yet full
    good.push(32.0, 32)
    bad.push(64.0, 32)
    good.push(0.0, 0)  # a sample without data does not count
    assert good.full and good.count == 60 and good.consistent()
    assert not bad.consistent()
    lo, hi = good.band()
    assert lo == pytest.approx(chi2.ppf(0.005, 1920)) and hi == pytest.approx(chi2.ppf(0.995, 1920))


def test_convergence_names_what_is_missing(model: Any) -> None:
    rom = model.rom
    verdict = convergence(rom, wide_prior(rom, ambient_c=22.0), NisWindow(10))
    assert not verdict.converged
    assert (
        "sensor 1σ" in verdict.reason
        and "field RMS" in verdict.reason
        and "NIS window 0/10" in verdict.reason
    )
    # the heat-capacity-weighted RMS of the prior's field σ: the uniform part (5 °C) plus the shape part
    assert verdict.field_rms_std_c > 5.0


def test_bad_arguments_name_the_field(model: Any) -> None:
    rom = model.rom
    est = StateEstimator(rom, wide_prior(rom, ambient_c=22.0))
    with pytest.raises(EstimatorError, match="h:"):
        est.predict(StepInput(-H, 22.0, 0.0, 0.0))
    with pytest.raises(EstimatorError, match="dt_s"):
        est.predict(StepInput(H, 22.0, 0.0, 0.0, dt_s=0.0))
    with pytest.raises(EstimatorError, match=r"inputs\.ambient_c"):
        est.predict(StepInput(H, float("nan"), 0.0, 0.0))
    with pytest.raises(EstimatorError, match="mask"):
        est.update(np.zeros(32), np.ones(31, bool))
    with pytest.raises(EstimatorError, match="measurement"):
        est.update(np.zeros(30))
    with pytest.raises(EstimatorError, match="offsets_c"):
        StateEstimator(rom, wide_prior(rom, ambient_c=22.0), offsets_c=np.zeros(3))
    with pytest.raises(EstimatorError, match=r"noise\.sigma_meas_c"):
        NoiseModel(sigma_meas_c=0.0)
    with pytest.raises(EstimatorError, match=r"noise\.h_rel"):
        NoiseModel(h_rel=(0.1, 0.2))
    with pytest.raises(EstimatorError, match=r"noise\.param_tau_s"):
        NoiseModel(param_tau_s=0.0)
    with pytest.raises(EstimatorError, match="estimate"):
        StateEstimator(rom, Estimate(np.zeros(3), np.eye(3), np.zeros((3, N_PARAMS))))


def test_rom_defect_covariance_is_small_and_positive_semidefinite(model: Any) -> None:
    rom, inputs = model.rom, _inputs(60)
    report = rom_defect_cov(rom, model.fe, [DefectCase(H, inputs, 22.0)])
    assert report.cov.shape == (rom.rank, rom.rank) and report.steps == 60
    np.testing.assert_allclose(report.cov, report.cov.T)
    assert np.linalg.eigvalsh(report.cov).min() > -1e-12 * np.abs(report.cov).max()
    # the reduced step from the projected full-FE state misses only thousandths of a degree at the sensors
    assert 0.0 < report.sensor_rms_c < 0.01 and report.outside_rms_c < 0.02
