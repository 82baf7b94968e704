"""Forecast: long horizons reach the steady state, the time constant matches a fitted exponential."""

from __future__ import annotations

import numpy as np
import pytest

from model.fem import FEModel, simulate, steady_state
from model.geometry import SpindleSpec
from model.growth import GrowthError, forecast_growth, thermal_modes
from model.heat import bearing_heat_w
from model.inputs import InputSeries
from model.thermoelastic import GrowthModel
from tests.model_growth.conftest import H_TABLE4

AMB = 20.0


def _heats(spec: SpindleSpec, speed: float) -> tuple[float, float]:
    return (
        float(bearing_heat_w(speed, 0.0, spec.bearings.front)),
        float(bearing_heat_w(speed, 0.0, spec.bearings.rear)),
    )


def _forecast(spec, fe, growth, field, horizons, speed=5000.0, dt_s=10.0):  # type: ignore[no-untyped-def]
    qf, qr = _heats(spec, speed)
    return forecast_growth(
        fe, growth, H_TABLE4, field_c=field, t_ref_c=AMB, ambient_c=AMB, q_front_w=qf, q_rear_w=qr,
        horizons_s=horizons, dt_s=dt_s,
    )  # fmt: skip


def test_long_horizon_reaches_steady_state(spec: SpindleSpec, fe: FEModel, growth: GrowthModel) -> None:
    fc = _forecast(spec, fe, growth, np.full(fe.n_nodes, AMB), (300.0, 900.0, 1800.0, 8 * 3600.0), dt_s=60.0)
    assert np.all(fc.now_um == 0.0)
    gap = np.abs(fc.at_horizon_um - fc.steady_um)
    assert np.all(gap[-1] < 1e-3 * np.abs(fc.steady_um))  # 8 h ~ 16 slowest time constants
    nose = growth.names.index("nose_axial")
    assert np.all(np.diff(fc.at_horizon_um[:, nose]) > 0)  # heating: the nose moves out monotonically
    assert fc.steady_um[nose] > fc.at_horizon_um[2, nose] > 0.5 * fc.steady_um[nose]


def test_forecast_from_steady_state_stays_there(spec: SpindleSpec, fe: FEModel, growth: GrowthModel) -> None:
    qf, qr = _heats(spec, 3000.0)
    t_ss = steady_state(fe, H_TABLE4, ambient_c=AMB, q_front_w=qf, q_rear_w=qr)
    fc = _forecast(spec, fe, growth, t_ss, (300.0, 1800.0), speed=3000.0)
    assert np.allclose(fc.at_horizon_um, fc.steady_um, rtol=1e-9, atol=1e-9)
    assert np.allclose(fc.now_um, fc.steady_um, rtol=1e-9, atol=1e-9)


def test_cooling_forecast_matches_direct_simulation(
    spec: SpindleSpec, fe: FEModel, growth: GrowthModel
) -> None:
    qf, qr = _heats(spec, 7000.0)
    hot = steady_state(fe, H_TABLE4, ambient_c=AMB, q_front_w=qf, q_rear_w=qr)
    fc = _forecast(spec, fe, growth, hot, (600.0, 1200.0), speed=0.0)  # spindle stopped: it cools down
    inputs = InputSeries(
        dt_s=10.0, ambient_c=np.full(120, AMB), q_front_w=np.zeros(120), q_rear_w=np.zeros(120)
    )
    fields = simulate(fe, H_TABLE4, inputs, hot)
    assert np.allclose(fc.at_horizon_um, growth.growth_um(fields[[60, 120]], AMB), rtol=1e-12)
    assert np.allclose(fc.steady_um, 0.0, atol=1e-9)


@pytest.mark.slow
def test_dominant_time_constant_matches_fitted_exponential(
    spec: SpindleSpec, fe: FEModel, growth: GrowthModel
) -> None:
    qf, qr = _heats(spec, 5000.0)
    fc = _forecast(spec, fe, growth, np.full(fe.n_nodes, AMB), (600.0,))
    tau = fc.tau_s[growth.names.index("nose_axial")]
    dt, n = 10.0, 2400  # 400 min step response
    inputs = InputSeries(
        dt_s=dt, ambient_c=np.full(n, AMB), q_front_w=np.full(n, qf), q_rear_w=np.full(n, qr)
    )
    y = growth.growth_um(simulate(fe, H_TABLE4, inputs, AMB), AMB)[:, growth.names.index("nose_axial")]
    t = np.arange(n + 1) * dt
    tail = (t > 150 * 60) & (t < 350 * 60)
    slope = np.polyfit(t[tail], np.log(fc.steady_um[growth.names.index("nose_axial")] - y[tail]), 1)[0]
    tau_fit = -1.0 / slope
    tau_be = dt / np.log1p(dt / tau)  # backward Euler's decay per step is 1 / (1 + dt/tau)
    assert tau_fit == pytest.approx(tau_be, rel=2e-3)
    assert 20 * 60 < tau < 45 * 60  # a 48 kJ/K spindle: tens of minutes (paper: steady after 25-30 min)
    assert tau == pytest.approx(fc.slowest_tau_s, rel=1e-12)  # the slowest mode dominates a cold start


def test_thermal_modes_are_e_orthonormal(fe: FEModel) -> None:
    modes = thermal_modes(fe, H_TABLE4, n_modes=4)
    gram = modes.vectors.T @ (fe.E @ modes.vectors)
    assert np.allclose(gram, np.eye(4), atol=1e-8)
    assert np.all(np.diff(modes.tau_s) < 0)


def test_horizon_not_a_multiple_of_the_step_is_named(
    spec: SpindleSpec, fe: FEModel, growth: GrowthModel
) -> None:
    with pytest.raises(GrowthError, match="horizons_s"):
        _forecast(spec, fe, growth, np.full(fe.n_nodes, AMB), (305.0,))
    with pytest.raises(GrowthError, match="field_c"):
        _forecast(spec, fe, growth, np.full(fe.n_nodes - 1, AMB), (300.0,))
