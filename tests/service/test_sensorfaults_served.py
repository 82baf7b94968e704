"""A stuck sensor channel through the real service (issue 40 part 4): the core's live state finds it from
its checks, leaves it out, says so in the log, ``/chtc``, ``/compensation`` (and its REST body), and takes it
back once its readings move and agree with the model again.

The served service (``simulator.served``) is fed the demo plan's plant run with channel 5 frozen at its
reading of minute 8 until minute 17 (quality ok: the DAQ does not flag it).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from api.schemas import compensation_out
from service.contracts.sensorfault import FaultKind
from service.settings import Settings
from simulator.served import feed, served_service

pytestmark = pytest.mark.slow

CHANNEL = 5
FROZEN = (48, 102)  # samples [from, to): minutes 8 to 17


def test_a_stuck_channel_is_found_said_and_taken_back(tmp_path: Path) -> None:
    url = f"sqlite:///{tmp_path / 'chtc.sqlite'}"
    logs: list[str] = []
    settings = Settings(compensation={"reference_c": 23.2})
    with served_service(database_url=url, settings=settings, feed_samples=0, on_event=logs.append) as s:
        samples = s.samples
        frozen = float(samples[FROZEN[0] - 1].temps_c[CHANNEL - 1])
        found_at = None
        for k, sample in enumerate(samples):
            if FROZEN[0] <= k < FROZEN[1]:
                temps = np.array(sample.temps_c, dtype=float)
                temps[CHANNEL - 1] = frozen
                sample = dataclasses.replace(sample, temps_c=temps)
            feed(s, sample)
            live = s.service.view.live
            faults = () if live is None else live.sensor_faults
            if found_at is None and faults:
                found_at = k
                (fault,) = faults
                assert (fault.channel, fault.kind) == (CHANNEL, FaultKind.STUCK)
                assert fault.since_t == pytest.approx(sample.t.timestamp())
                comp = s.service.compensation()
                assert comp is not None and comp.sensor_faults == faults
                chtc = s.service.chtc()
                assert chtc is None or chtc.sensor_faults == faults
                body = compensation_out(comp, sample.t, spindle_id="sp").model_dump()
                assert body["sensor_faults"][0]["channel"] == CHANNEL
                assert body["sensor_faults"][0]["kind"] == "stuck"
                assert body["sensor_faults"][0]["since"] == sample.t
        assert found_at is not None, "the stuck channel was never found"
        assert found_at - FROZEN[0] <= 31  # its 5-min window (bar: 30 min)
        live = s.service.view.live
        assert live is not None and live.sensor_faults == (), "not taken back after it moved again"
        comp = s.service.compensation()
        assert comp is not None and comp.sensor_faults == ()
    said = [line for line in logs if f"sensor channel {CHANNEL}" in line]
    assert any("left out of the live state as stuck since" in line for line in said), logs[-20:]
    assert any("taken back into the live state" in line for line in said), said
