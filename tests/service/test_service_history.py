"""The running service keeps measured and predicted temperatures per sample for ``GET /sensors/history``."""

from __future__ import annotations

from dataclasses import replace
from datetime import UTC, datetime, timedelta

import numpy as np

from drivers.quality import Quality
from model.plant import Segment
from service.contracts.records import IdentificationData
from service.contracts.snapshots import ConditionSnapshot, ConditionState, IdentificationRecord
from service.core.machine import Restored, ServiceCore
from service.host.runtime import core_config
from service.serve.views import data_to_record
from service.settings import Settings
from service.shell.service import SoftSensorService

from .conftest import plant_run, samples_of


def _last_identification(h: np.ndarray) -> IdentificationRecord:
    t = datetime(2026, 1, 5, 7, 0, tzinfo=UTC)
    cond = ConditionSnapshot(
        id=1,
        speed_rpm=3000.0,
        torque_nm=5.0,
        ambient_c=22.0,
        since=t - timedelta(hours=1),
        state=ConditionState.STABLE,
    )
    data = IdentificationData(
        id=1,
        condition_id=cond.id,
        started_at=t,
        finished_at=t,
        window_start=t - timedelta(hours=1),
        window_end=t,
        reason="condition-change",
        outcome="ok",
        method="hybrid",
        model_version="m",
        h=list(h),
        ci95_lo=list(0.9 * h),
        ci95_hi=list(1.1 * h),
        identified=[True] * 7,
        f=0.01,
        fit=0.99,
        rmse_c=0.1,
        nfev=10,
        duration_s=0.1,
        n_sensors_used=32,
    )
    return data_to_record(data, cond)


def test_service_keeps_measured_and_predicted_per_sample_with_masked_channels_as_nan(loaded_model) -> None:
    h = np.array([88.2, 46.3, 68.5, 46.7, 52.1, 70.2, 16.5])
    core = ServiceCore(
        core_config(Settings()),
        model=loaded_model,
        restored=Restored(last=_last_identification(h)),
    )
    svc = SoftSensorService(core, worker=None, history_capacity=15)
    samples = samples_of(plant_run([Segment(300.0, 3000.0, 5.0, 22.0)], seed=4))[:20]
    quality = np.full(32, int(Quality.OK), dtype=np.uint8)
    quality[4] = int(Quality.OPEN_CIRCUIT)
    samples[-1] = replace(samples[-1], quality=quality)
    predicted = []
    for smp in samples:
        svc.on_sample(smp)
        predicted.append([r.predicted_c for r in svc.sensors()])

    hist = svc.sensor_history(None)
    assert hist.capacity == 15 and hist.channels == tuple(range(1, 33))
    assert hist.names[0] == loaded_model.spec.sensors[0].name
    assert hist.t == tuple(s.t for s in samples[-15:])  # the oldest 5 are gone
    np.testing.assert_allclose(hist.measured_c[:-1], np.array([s.temps_c for s in samples[-15:-1]]))
    assert np.isnan(hist.measured_c[-1, 4]) and np.isfinite(np.delete(hist.measured_c[-1], 4)).all()
    np.testing.assert_allclose(hist.predicted_c, np.array(predicted[-15:]))
    assert np.ptp(hist.predicted_c[:, 0]) > 0  # the prediction moves with the live state, not one copy

    later = svc.sensor_history(samples[-3].t)
    assert later.t == (samples[-2].t, samples[-1].t)
