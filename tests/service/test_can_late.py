"""The DAQ delivers before the CAN sensor does (CAN down at start, or ``chtc identify`` without a CAN log).

Found in review of issue 12 (items 1, 18, 22): the live state started at the first sample with an ambient
temperature and took its NaN speed/torque; the next sample raised ``InputError: q_front_w: contains
non-finite values`` out of the core's sample handling. In ``chtc run`` that exception ended the acquisition's
task group, so the DAQ and CAN loops stopped silently and `/healthz` then reported the (healthy) DAQ as
`down`.

The core is driven with events first (what its view holds), then the real service (``simulator.served``:
core, shell, SQLite) takes the samples as the acquisition hands them over, and what it serves is checked.
"""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np

from drivers.ringbuffer import Sample
from model.plant import Segment
from service.core.events import SampleReceived
from service.core.machine import ServiceCore
from service.host.runtime import core_config
from service.modelload import LoadedModel
from service.settings import Settings
from simulator.served import Plan, feed, plant_samples, served_service

PLAN = Plan(profile=(Segment(780.0, 3000.0, 5.0, 22.0),))  # 13 min: one identification (first window 7 min)
N_SILENT = 6  # the first minute: the DAQ answers, CAN does not (yet)


def _without_can(sample: Sample) -> Sample:
    return replace(sample, speed_rpm=math.nan, torque_nm=math.nan, can_ok=False)


def test_samples_without_speed_and_torque_do_not_break_the_core(loaded_model: LoadedModel) -> None:
    samples = plant_samples(PLAN)
    core = ServiceCore(core_config(Settings()), model=loaded_model, history_capacity=1000)

    for n, s in enumerate(samples[:N_SILENT], start=1):
        core.handle(SampleReceived(f"sample-{n}", _without_can(s)))
        assert core.view().live is None  # no speed/torque yet: the heat input is unknown
    for n, s in enumerate(samples[N_SILENT : N_SILENT + 3], start=N_SILENT + 1):
        core.handle(SampleReceived(f"sample-{n}", s))

    # the live state started at the first sample with speed and torque, and advances from there
    live = core.view().live
    assert live is not None
    assert live.t > samples[N_SILENT].t.timestamp()
    assert np.isfinite(loaded_model.fe.sensor_op @ live.field_c).all()


def test_samples_without_speed_and_torque_do_not_break_the_service(tmp_path: Path) -> None:
    with served_service(database_url=f"sqlite:///{tmp_path / 'chtc.db'}", plan=PLAN, feed_samples=0) as s:
        for smp in s.samples[:N_SILENT]:
            feed(s, _without_can(smp))  # raised InputError out of the core before the fix
        assert s.service.chtc() is None
        assert any(r.startswith("can_no_good_data") for r in s.service.ready().reasons)
        for smp in s.samples[N_SILENT:]:
            feed(s, smp)
        snap = s.service.chtc()
        assert s.service.ready().ready
        # identified once CAN came up: the live state runs from the first sample with speed and torque
        assert snap is not None and snap.condition.speed_rpm == 3000.0
        assert snap.condition.since == s.samples[N_SILENT].t
        predicted = [r.predicted_c for r in s.service.sensors()]
        assert all(p is not None and math.isfinite(p) for p in predicted)
        assert np.isfinite(s.service.field("now").temps_c).all()


def test_no_can_at_all_gives_no_identification_and_no_error(tmp_path: Path) -> None:
    with served_service(database_url=f"sqlite:///{tmp_path / 'chtc.db'}", plan=PLAN, feed_samples=0) as s:
        for smp in s.samples:
            feed(s, _without_can(smp))
        assert s.service.chtc() is None
        assert s.service.list_identifications(since=None, until=None, limit=10, offset=0).total == 0
        reasons = s.service.ready().reasons
        assert [r.split(":")[0] for r in reasons] == ["can_no_good_data"], reasons
