"""The probe reading's Kalman update of the mechanical posterior (``service.estimate.probe``, pure): it
tightens the posterior and moves it toward a synthetic truth, a reading beyond the gate is flagged and not
absorbed, and a replay of the accepted readings gives the same posterior as taking them one by one."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta

import numpy as np
import pytest

from service.contracts.mechanics import MechanicsCalibration
from service.contracts.probe import ProbeError, ProbeMeasurement
from service.estimate.probe import (
    absorb,
    predict,
    prior_covariance,
    prior_mean,
    replay,
    replay_state,
    start_state,
)

AT = datetime(2026, 11, 27, 8, 0, tzinfo=UTC)
# the feature row's scale at a hot spindle (µm): free and held mounts, other/shaft/housing α groups; held
# pulls the nose back (the 5000 rpm nose growth goes +8.2 µm free -> −2.6 µm held, docs/growth.md)
FREE = np.array([2.0, 9.0, -3.0])
HELD = np.array([1.0, -1.0, -2.5])


def _features(rng: np.random.Generator, heat: float) -> np.ndarray:
    """A feature row for a field at ``heat`` (0 cold .. 1 hot), the groups' shares varying with the duty."""
    mix = rng.uniform(0.6, 1.4, size=(2, 3))
    return heat * np.vstack([FREE, HELD]) * mix


def _truth(rng: np.random.Generator) -> np.ndarray:
    return np.array([rng.uniform(0.05, 0.95), 1.0 + rng.normal(0, 0.03), 1.0 + rng.normal(0, 0.03)])


def _growth_sd(f: np.ndarray, x: np.ndarray, cov: np.ndarray) -> float:
    _, h = predict(f, x)
    return float(np.sqrt(h @ cov @ h))


def test_hourly_readings_tighten_the_posterior_and_move_it_toward_the_truth() -> None:
    better = 0
    for seed in range(20):
        rng = np.random.default_rng(seed)
        truth = _truth(rng)
        x, cov = prior_mean(), prior_covariance()
        f_test = _features(rng, 0.8)
        err0 = abs(predict(f_test, x)[0] - predict(f_test, truth)[0])
        sd0 = _growth_sd(f_test, x, cov)
        for _ in range(8):  # a shift of hourly readings, 1 µm 1σ
            f = _features(rng, rng.uniform(0.2, 1.0))
            y = predict(f, truth)[0] + rng.normal(0.0, 1.0)
            up = absorb(x, cov, f, y, 1.0)
            assert up.accepted
            assert np.trace(up.cov) < np.trace(cov)  # every reading tightens
            x, cov = up.x, up.cov
        sd1 = _growth_sd(f_test, x, cov)
        err1 = abs(predict(f_test, x)[0] - predict(f_test, truth)[0])
        assert sd1 < 0.5 * sd0, (seed, sd0, sd1)
        assert err1 <= 3.0 * sd1 + 0.5, (seed, err1, sd1)  # the truth inside the tightened band
        better += err1 < err0
    assert better >= 16, better


def test_a_reading_beyond_the_gate_is_flagged_and_not_absorbed() -> None:
    rng = np.random.default_rng(7)
    truth = _truth(rng)
    x, cov = prior_mean(), prior_covariance()
    f = _features(rng, 0.9)
    y = predict(f, truth)[0]
    up = absorb(x, cov, f, y + 60.0, 1.0, gate_sigma=3.0)  # a crash moved the tool by 60 µm
    assert not up.accepted
    assert abs(up.innovation_um) > 3.0 * up.sigma_um
    assert np.array_equal(up.x, x) and np.array_equal(up.cov, cov)
    forced = absorb(x, cov, f, y + 60.0, 1.0, gate_sigma=None)
    assert forced.accepted and not np.array_equal(forced.x, x)
    ok = absorb(x, cov, f, y, 1.0, gate_sigma=3.0)
    assert ok.accepted and abs(ok.innovation_um) <= 3.0 * ok.sigma_um


def test_replay_of_the_accepted_readings_equals_taking_them_one_by_one() -> None:
    rng = np.random.default_rng(3)
    truth = _truth(rng)
    x, cov = prior_mean(), prior_covariance()
    kept = []
    for k in range(6):
        f = _features(rng, rng.uniform(0.2, 1.0))
        y = predict(f, truth)[0] + rng.normal(0, 0.5) + (80.0 if k == 3 else 0.0)
        up = absorb(x, cov, f, y, 0.25 + 0.1)
        kept.append(
            ProbeMeasurement(
                at=AT + timedelta(hours=k),
                axial_um=y,
                sd_um=0.5,
                features=tuple(tuple(float(v) for v in r) for r in f),
                field_var_um2=0.1,
                predicted_um=up.predicted_um,
                sigma_um=up.sigma_um,
                innovation_um=up.innovation_um,
                accepted=up.accepted,
            )
        )
        x, cov = up.x, up.cov
    assert [m.accepted for m in kept] == [True, True, True, False, True, True]
    rx, rcov = replay(prior_mean(), prior_covariance(), kept)
    assert np.allclose(rx, x, rtol=0, atol=1e-12) and np.allclose(rcov, cov, rtol=0, atol=1e-12)


@pytest.mark.parametrize(
    ("features", "y", "var", "match"),
    [
        (np.ones((3, 3)), 1.0, 1.0, "features"),
        (np.full((2, 3), np.nan), 1.0, 1.0, "features"),
        (np.ones((2, 3)), float("nan"), 1.0, "axial_um"),
        (np.ones((2, 3)), 1.0, 0.0, "variance"),
    ],
)
def test_bad_readings_are_refused_naming_the_field(
    features: np.ndarray, y: float, var: float, match: str
) -> None:
    with pytest.raises(ProbeError, match=match):
        absorb(prior_mean(), prior_covariance(), features, y, var)


def test_a_restart_replays_the_accepted_readings_after_the_commissioning_only() -> None:
    from typing import Any, cast

    from service.serve.compensation import GrowthServer

    rng = np.random.default_rng(11)
    truth = _truth(rng)
    cal = MechanicsCalibration(
        x=(0.5, 1.0, 1.0),
        cov=tuple(tuple(float(v) for v in r) for r in prior_covariance()),
        at=AT,
        set_by="test",
        source="cli",
    )

    def reading(at: datetime, accepted: bool) -> ProbeMeasurement:
        f = _features(rng, 0.8)
        y = predict(f, truth)[0]
        return ProbeMeasurement(
            at=at,
            axial_um=y,
            sd_um=0.5,
            features=tuple(tuple(float(v) for v in r) for r in f),
            field_var_um2=0.0,
            predicted_um=0.0,
            sigma_um=1.0,
            innovation_um=0.0,
            accepted=accepted,
        )

    before = reading(AT - timedelta(hours=1), True)  # measured before the commissioning: not replayed
    flagged = reading(AT + timedelta(hours=1), False)
    after = reading(AT + timedelta(hours=2), True)
    server = GrowthServer(cast(Any, None), mechanics=cal, probes=(before, flagged, after))
    got = server.mechanics
    assert got is not None and server.commissioning is cal
    from service.serve.compensation import _default_probe_tuning

    tuning = _default_probe_tuning()
    start = start_state(cal.mean, cal.covariance, AT.timestamp(), tuning)
    want_x, want_cov = replay_state(start, [flagged, after], tuning).mechanics  # θ and b jointly
    assert np.allclose(got.mean, want_x, rtol=0, atol=1e-12)
    assert np.allclose(got.covariance, want_cov, rtol=0, atol=1e-12)
    assert got.report["probe_readings_absorbed"] == 1
    off = server.fixture_offset
    assert off is not None and off.readings == 1 and off.sd_um < tuning.offset_sd_um
    assert [m.at for m in server.probes()] == [after.at, flagged.at, before.at]
    assert GrowthServer(cast(Any, None), mechanics=cal, probes=(before,)).mechanics is cal
    alone = GrowthServer(cast(Any, None), probes=(after,)).mechanics  # no commissioning: from the prior
    assert alone is not None and alone.source == "prior" and server.commissioning is not None
