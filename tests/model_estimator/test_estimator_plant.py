"""The filter on the virtual plant (finer mesh, its own truth, σ = 0.15 °C, 0.01 °C quantisation): no
inverse crime. Profile: 5 min idle, 3000 rpm 60 min, 4000 rpm 45 min (conftest.PROFILE)."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from model.estimator import (
    NisWindow,
    NoiseModel,
    StateEstimator,
    convergence,
    heated_prior,
    matched_sigma_c,
    wide_prior,
)
from tests.model_estimator.conftest import PlantData

pytestmark = pytest.mark.slow  # the session plant_data fixture: a virtual-plant run, ~65 s at load 8

# an identified H is off by ~20 % (1σ) on the poorly determined coefficients, the filter's default h_rel;
# this draw is a harsh one: 1.50, 0.60, 1.09, 0.89, 0.91, 0.96, 0.67 (three coefficients ~2σ off)
H_ERROR = np.exp(0.2 * np.random.default_rng(3).standard_normal(7))
SAMPLES_PER_MIN = 6


def _run(
    model: Any,
    data: PlantData,
    *,
    start: int = 0,
    h_factor: np.ndarray | None = None,
    front_scale: float = 1.0,
) -> dict[str, Any]:
    """Filter the plant's samples from ``start`` on (wide prior at the ambient); per sample the NIS, dof,
    window verdict, state error at the sensors vs the noise-free truth and its σ."""
    run = data.run
    est = StateEstimator(model.rom, wide_prior(model.rom, ambient_c=float(run.ambient_c[start])))
    window = NisWindow(30)
    first = est.update(run.temps_c[start])
    window.push(first.nis, first.dof)
    out: dict[str, list[Any]] = {k: [] for k in ("nis", "dof", "consistent", "err", "std", "converged")}
    for k in range(start, data.inputs.n_steps):
        u = data.step_input(k, h_factor)
        u = type(u)(u.h, u.ambient_c, u.q_front_w * front_scale, u.q_rear_w, u.dt_s)
        res = est.step(u, run.temps_c[k + 1])
        window.push(res.nis, res.dof)
        out["nis"].append(res.nis)
        out["dof"].append(res.dof)
        out["consistent"].append(window.consistent() if window.full else None)
        out["err"].append(est.sensors_mean() - run.truth_c[k + 1])
        out["std"].append(est.sensors_std())
        out["converged"].append(convergence(model.rom, est.estimate, window).converged)
    arrays = {k: np.asarray(v) for k, v in out.items()}
    arrays["estimator"] = est
    return arrays


@pytest.mark.parametrize("h_error", [False, True], ids=["true-H", "H-off-20pct"])
def test_nis_is_consistent_with_chi_square_on_the_virtual_plant(
    model: Any, plant_data: PlantData, h_error: bool
) -> None:
    """Measured (2026-11-24, rank 46, exact held step): mean NIS/dof 0.967 (true H) and 0.973 (H off by the
    harsh draw); 96.5 % and 97.2 % of the 30-sample windows inside the 99 % χ² band."""
    res = _run(model, plant_data, h_factor=H_ERROR if h_error else None)
    ratio = res["nis"].sum() / res["dof"].sum()
    assert 0.9 <= ratio <= 1.1, ratio
    windows = [c for c in res["consistent"] if c is not None]
    assert np.mean(windows) >= 0.9, np.mean(windows)


def test_a_missing_heat_source_is_reported_by_the_nis_window(model: Any, plant_data: PlantData) -> None:
    """The model gets half the front bearing's heat (beyond its 10 % load error): the windowed NIS leaves
    the band (measured 2026-11-24: 97 % of the windows outside it, mean NIS/dof 1.30)."""
    res = _run(model, plant_data, front_scale=0.5)
    windows = [c for c in res["consistent"] if c is not None]
    assert np.mean(windows) < 0.1
    assert res["nis"].sum() / res["dof"].sum() > 1.15


def _h_draw(seed: int) -> np.ndarray:
    """Relative H error of an identification: log-normal, 20 % (the filter's default ``h_rel``)."""
    return np.exp(0.2 * np.random.default_rng(seed).standard_normal(7))


def _field_check(model: Any, data: PlantData, res: dict[str, Any], start: int, h_factor: np.ndarray) -> Any:
    """(fraction of nodes within 2σ, filter RMS error, open-loop RMS error) of the field at the run's end
    against the plant's field interpolated onto the service mesh; the open loop starts uniform at the mean of
    the first sample (today's live state)."""
    est = res["estimator"]
    field_err = est.field_mean() - data.final_field_c
    inside = float(np.mean(np.abs(field_err) <= 2.0 * est.field_std()))
    n_steps = data.inputs.n_steps
    h0 = data.run.h_true[start] * h_factor
    t0 = float(data.run.temps_c[start].mean())
    open_loop = model.rom.lift(model.rom.simulate_state(h0, data.inputs.slice(start, n_steps), t0)[-1])
    ol_rms = float(np.sqrt(np.mean((open_loop - data.final_field_c) ** 2)))
    return inside, float(np.sqrt(np.mean(field_err**2))), ol_rms


@pytest.mark.parametrize("start_min", [30, 60, 90])
def test_restart_on_a_warm_spindle_converges(model: Any, plant_data: PlantData, start_min: int) -> None:
    """The service starts at minute 30/60/90 of the profile (sensors 5–10 °C above the ambient) from a wide
    prior at the cold uniform ambient, with H off by a typical draw (1.03, 0.97, 1.14, 1.02, 0.90, 1.07,
    1.30). Measured (2026-11-24, rank 46, exact held step) N = 1 min: from then on ≥ 90 % of the sensors'
    state errors vs the noise-free truth are within 2σ (measured 0.95–0.97) and none beyond 5σ (measured
    ≤ 3.5σ); the convergence test passes after 5 min (its NIS window; measured 29 samples); at the run's
    end the whole field (the plant's field interpolated onto the service mesh) is within 2σ at ≥ 99 % of
    the nodes (measured 100 %), and its RMS error is under half the open-loop model's from a uniform start
    (measured 0.11 vs 0.95 °C at start 60)."""
    start = start_min * SAMPLES_PER_MIN
    h_factor = _h_draw(0)
    res = _run(model, plant_data, start=start, h_factor=h_factor)
    z = np.abs(res["err"]) / res["std"]
    after = z[SAMPLES_PER_MIN:]
    assert after.max() <= 5.0, after.max()
    assert np.mean(after <= 2.0) >= 0.9, np.mean(after <= 2.0)
    converged_at = int(np.argmax(res["converged"])) + 1
    assert res["converged"].any() and converged_at <= 6 * SAMPLES_PER_MIN, converged_at
    assert res["converged"][converged_at:].mean() > 0.9  # and it stays converged
    inside, kf_rms, ol_rms = _field_check(model, plant_data, res, start, h_factor)
    assert inside >= 0.99, inside
    assert kf_rms < 0.5 * ol_rms, (kf_rms, ol_rms)


def test_restart_field_coverage_over_eight_h_errors(model: Any, plant_data: PlantData) -> None:
    """Start at minute 60, eight 20 % H-error draws: the field at the end is within 2σ at ≥ 99 % of the nodes
    for most draws (measured 2026-11-24: 6 of 8 at 100 %); draws with two or three coefficients ~2σ off
    leave the interior's error up to 2.5σ (measured 0.75 and 0.79 of the nodes within 2σ): the linearised
    consider covariance is a 1σ statement, not a bound."""
    coverage = []
    for seed in range(8):
        h_factor = _h_draw(seed)
        res = _run(model, plant_data, start=60 * SAMPLES_PER_MIN, h_factor=h_factor)
        coverage.append(_field_check(model, plant_data, res, 60 * SAMPLES_PER_MIN, h_factor)[0])
    assert np.median(coverage) >= 0.99, coverage
    assert min(coverage) >= 0.7, coverage


def test_measurement_noise_is_recovered_from_the_innovations(model: Any, plant_data: PlantData) -> None:
    """A filter told σ = 0.3 °C (twice the plant's 0.15 °C): covariance matching over the innovations after
    the first 10 min gives back the plant's noise (measured 0.145 °C; 0.148 and 0.150 when told 0.15 and
    0.08 °C)."""
    run = plant_data.run
    est = StateEstimator(
        model.rom,
        wide_prior(model.rom, ambient_c=float(run.ambient_c[0])),
        noise=NoiseModel(sigma_meas_c=0.3),
    )
    est.update(run.temps_c[0])
    innov, std = [], []
    for k in range(plant_data.inputs.n_steps):
        res = est.step(plant_data.step_input(k), run.temps_c[k + 1])
        innov.append(res.innovation)
        std.append(res.predicted_std_c)
    sigma = matched_sigma_c(np.asarray(innov)[60:], np.asarray(std)[60:], est.noise.r_var)
    # the estimate is σ_meas² + σ_model² seen by the data: the plant's noise plus what the model misses
    assert 0.14 <= sigma <= 0.17, sigma


@pytest.mark.parametrize("lead_min", [5, 10])
def test_heated_prior_pins_the_interior_sooner_than_the_isotropic_one(
    model: Any, plant_data: PlantData, lead_min: int
) -> None:
    """A restart ``lead_min`` before the run's end (4000 rpm, warm), true H: the field's RMS error at the end
    against the plant's field, from ``heated_prior`` vs ``wide_prior``. Measured 2026-11-24: 0.22 vs 0.80 °C
    (5 min) and 0.20 vs 0.50 °C (10 min); both within 2σ at every node."""
    run, n = plant_data.run, plant_data.inputs.n_steps
    start = n - lead_min * SAMPLES_PER_MIN
    rms = {}
    for name, prior in (
        ("heated", heated_prior(model.rom, ambient_c=float(run.ambient_c[start]))),
        ("wide", wide_prior(model.rom, ambient_c=float(run.ambient_c[start]))),
    ):
        est = StateEstimator(model.rom, prior)
        est.update(run.temps_c[start])
        for k in range(start, n):
            est.step(plant_data.step_input(k), run.temps_c[k + 1])
        err = est.field_mean() - plant_data.final_field_c
        assert np.mean(np.abs(err) <= 2.0 * est.field_std()) >= 0.99
        rms[name] = float(np.sqrt(np.mean(err**2)))
    assert rms["heated"] < 0.6 * rms["wide"], rms
