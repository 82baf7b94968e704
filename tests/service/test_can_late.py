"""The DAQ delivers before the CAN sensor does (CAN down at start, or ``chtc identify`` without a CAN log).

Found in review of issue 12 (items 1, 18, 22): the live state started at the first sample with an ambient
temperature and took its NaN speed/torque; the next sample raised ``InputError: q_front_w: contains
non-finite values`` out of the core's sample handling. In ``chtc run`` that exception ended the acquisition's
task group, so the DAQ and CAN loops stopped silently and `/healthz` then reported the (healthy) DAQ as
`down`.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from model.plant import Segment
from service.engine.core import ServiceCore
from service.engine.events import SampleReceived
from service.engine.offline import run_offline
from service.engine.runtime import core_config
from service.modelload import LoadedModel
from service.settings import Settings

from .conftest import plant_run, samples_of


def test_samples_without_speed_and_torque_do_not_break_the_core(loaded_model: LoadedModel) -> None:
    run = plant_run([Segment(1200.0, 3000.0, 5.0, 22.0)])
    samples = samples_of(run)
    n_silent = 6  # the first minute: the DAQ answers, CAN does not (yet)
    silent = [replace(s, speed_rpm=math.nan, torque_nm=math.nan, can_ok=False) for s in samples[:n_silent]]
    core = ServiceCore(core_config(Settings()), model=loaded_model, history_capacity=1000)

    for n, s in enumerate(silent, start=1):
        core.handle(SampleReceived(f"sample-{n}", s))
        assert core.view().live is None  # no speed/torque yet: the heat input is unknown
    for n, s in enumerate(samples[n_silent : n_silent + 3], start=n_silent + 1):
        core.handle(SampleReceived(f"sample-{n}", s))

    # the live state started at the first sample with speed and torque, and advances from there
    live = core.view().live
    assert live is not None
    assert live.t > samples[n_silent].t.timestamp()
    assert np.isfinite(loaded_model.fe.sensor_op @ live.field_c).all()


def test_no_can_at_all_gives_no_identification_and_no_error(loaded_model: LoadedModel) -> None:
    run = plant_run([Segment(1200.0, 3000.0, 5.0, 22.0)])
    samples = [replace(s, speed_rpm=math.nan, torque_nm=math.nan, can_ok=False) for s in samples_of(run)]

    result = run_offline(samples, model=loaded_model, config=core_config(Settings()))

    assert result.records == []
