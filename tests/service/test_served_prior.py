"""The served modes' per-condition fits take a prior (``service.identify.prior``), the paper's protocol does
not: the core's launched jobs, driven with virtual-plant samples (no job run)."""

from __future__ import annotations

from datetime import UTC, datetime
from typing import Any

import numpy as np
import pytest

from model.hmap import NODES
from model.identify_prior import COLD_SD_LOG, condition_prior
from model.plant import Segment
from service.contracts.mode import IdentificationMode
from service.core.machine import ServiceCore
from service.identify.prior import job_prior
from service.identify.speedmap import SpeedMap
from tests.engine_config import PER_CONDITION_10_20, product_core

from .conftest import plant_run, samples_of
from .drive import feed, launches

# the product's defaults but the per-condition protocol with 10-min windows (PER_CONDITION_10_20: these tests'
# timings) and without the sensor offset calibration (the tests replace the mode where they need a served one)
CFG = product_core(identification={**PER_CONDITION_10_20, "offset_calibration": False})


@pytest.fixture(scope="module")
def samples():  # type: ignore[no-untyped-def]
    """Idle until the live state converged, then 3000 rpm for 12 min (a per-condition job at 10 min)."""
    return samples_of(plant_run([Segment(1000.0, 0.0, 0.0, 22.0), Segment(720.0, 3000.0, 5.0, 22.0)], seed=5))


def _per_condition_launches(model: Any, samples: Any, mode: IdentificationMode) -> list[Any]:
    from dataclasses import replace

    core = ServiceCore(replace(CFG, mode=mode), model=model)
    return [ln for ln in launches(feed(core, samples)) if ln.request.speed_map is None]


def test_the_papers_protocol_fits_without_a_prior(loaded_model, samples) -> None:  # type: ignore[no-untyped-def]
    jobs = _per_condition_launches(loaded_model, samples, IdentificationMode.PER_CONDITION)
    assert jobs and all(ln.request.prior is None for ln in jobs)


def test_combined_mode_fits_with_the_cold_prior_before_any_map(loaded_model, samples) -> None:  # type: ignore[no-untyped-def]
    jobs = _per_condition_launches(loaded_model, samples, IdentificationMode.COMBINED)
    assert jobs
    for ln in jobs:
        prior = ln.request.prior
        assert prior is not None
        cold = condition_prior(loaded_model.spec, 3000.0, box=loaded_model.ref.h_box)
        # the condition's speed is the detector's (about 3000 rpm): the physics curves there, σ ln 3
        np.testing.assert_allclose(np.sqrt(np.diag(prior.log_cov)), COLD_SD_LOG)
        np.testing.assert_allclose(prior.log_mean, cold.log_mean, atol=0.02)


def _map(mean: Any, cov: Any) -> SpeedMap:
    return SpeedMap(
        family="nodes",
        mean=mean,
        cov=cov,
        visited_rpm=np.array([3000.0]),
        visited_s=np.array([600.0]),
        fitted_at=datetime(2026, 3, 2, tzinfo=UTC),
    )


def test_a_map_without_data_adds_nothing_and_one_with_data_narrows_the_prior(loaded_model) -> None:  # type: ignore[no-untyped-def]
    spec, box = loaded_model.spec, loaded_model.ref.h_box
    cold_map = NODES.prior(spec)
    cold = condition_prior(spec, 3000.0, box=box)
    same = job_prior(
        spec, box, 3000.0, 20.0, speed_map=_map(cold_map.mean, cold_map.cov), map_cold=cold_map, weight=0.25
    )
    np.testing.assert_allclose(same.log_cov, cold.log_cov, atol=1e-9)
    np.testing.assert_allclose(same.log_mean, cold.log_mean, atol=1e-9)
    # a posterior that knows every node to ±0.05 in ln H: the prior at 3000 rpm narrows, still judged
    # against the cold band
    post = np.linalg.inv(np.linalg.inv(cold_map.cov) + np.eye(cold_map.mean.size) / 0.05**2)
    narrow = job_prior(
        spec, box, 3000.0, 20.0, speed_map=_map(cold_map.mean, post), map_cold=cold_map, weight=0.25
    )
    assert np.all(np.diag(narrow.log_cov) < 0.1 * COLD_SD_LOG**2)
    np.testing.assert_allclose(narrow.reference_var, COLD_SD_LOG**2)
    assert "speed map" in narrow.source
