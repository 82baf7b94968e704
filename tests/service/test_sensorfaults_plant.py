"""Sensor faults on the virtual plant (issue 40 part 4): the plant's own fault injection (``ChannelFault``
"drift" and "stuck", not flagged by the DAQ) through the filtered live state, whose monitor
(``service.estimate.sensorfaults``) must find them (stuck within 30 min, drift before 1 °C) and raise
nothing on the clean run (the 105-min profile of tests.model_estimator.conftest: 5 min idle, 3000 rpm 60 min,
4000 rpm 45 min)."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from model.plant import ChannelFault, PlantRun, VirtualPlant
from service.contracts.sensorfault import FaultKind
from service.estimate.state import FilteredState
from tests.model_estimator import conftest as est_conftest

pytestmark = pytest.mark.slow

START_S = 1200.0  # the fault starts at minute 20
CHANNEL = 10


@pytest.fixture(scope="module")
def model() -> Any:
    return est_conftest.model.__wrapped__()  # type: ignore[attr-defined]


def _run(model: Any, faults: tuple[ChannelFault, ...]) -> PlantRun:
    plant = VirtualPlant(model.spec, noise_c=0.15, seed=11, steady_tol_c=0.0, faults=faults)
    return plant.run(list(est_conftest.PROFILE), dt_s=10.0, rng=np.random.default_rng(2026))


def _changes(model: Any, run: PlantRun) -> list[tuple[float, int, str, bool]]:
    state = FilteredState(model.rom, model.spec, h=run.h_true[0])
    inputs = (float(run.ambient_c[0]), float(run.speed_rpm[0]), float(run.torque_nm[0]))
    state.initialize(0.0, inputs, run.temps_c[0], None)
    out = []
    for k in range(1, run.times_s.size):
        upd = state.push(
            float(run.times_s[k]),
            ambient_c=float(run.ambient_c[k]),
            speed_rpm=float(run.speed_rpm[k]),
            torque_nm=float(run.torque_nm[k]),
            temps_c=run.temps_c[k],
        )
        out += [(c.t, c.fault.channel, c.fault.kind.value, c.recovered) for c in upd.faults]
    return out


def test_the_plants_drift_fault_walks_the_reading_off_and_is_found_before_one_degree(model: Any) -> None:
    run = _run(model, (ChannelFault(CHANNEL, "drift", START_S, rate_c_per_h=0.5),))
    gained = run.temps_c[:, CHANNEL - 1] - run.truth_c[:, CHANNEL - 1]
    assert gained[-1] == pytest.approx(0.5 * (run.times_s[-1] - START_S) / 3600.0, abs=0.6)
    changes = _changes(model, run)
    assert changes and changes[0][1:] == (CHANNEL, FaultKind.DRIFT.value, False), changes
    assert 0.5 * (changes[0][0] - START_S) / 3600.0 < 1.0
    assert [c for c in changes if c[1] != CHANNEL] == []


def test_the_plants_stuck_fault_is_found_within_30_min(model: Any) -> None:
    run = _run(model, (ChannelFault(CHANNEL, "stuck", START_S),))
    changes = _changes(model, run)
    assert changes and changes[0][1:] == (CHANNEL, FaultKind.STUCK.value, False), changes
    assert changes[0][0] - START_S <= 1800.0
    assert [c for c in changes if c[1] != CHANNEL] == []


def test_the_clean_run_raises_no_alarm(model: Any) -> None:
    assert _changes(model, _run(model, ())) == []
