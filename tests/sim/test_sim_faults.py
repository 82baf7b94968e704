"""Fault schedule and controller: parsing, timing by an injected clock, one-shot faults, channel effects."""

from __future__ import annotations

import math

import numpy as np
import pytest

from drivers.sim.faults import (
    Fault,
    FaultController,
    FaultKind,
    FaultSpecError,
    apply_channel_faults,
    parse_fault,
)
from tests.sim.simhelpers import FakeClock


def test_parse_fault_text() -> None:
    f = parse_fault("open:ch=5+6,at=10,for=20")
    assert f == Fault(FaultKind.OPEN_CIRCUIT, (5, 6), at_s=10.0, for_s=20.0)
    assert parse_fault("exception:code=6").param() == 6
    assert parse_fault("unknown-id:id=0x7E1").param() == 0x7E1
    assert parse_fault("counter-gap").param() == 3


@pytest.mark.parametrize(
    ("text", "field"),
    [
        ("bogus", "kind"),
        ("open", "ch"),
        ("drop:for=-1", "for"),
        ("hang:at=x", "at"),
        ("hang:colour=red", "colour"),
    ],
)
def test_bad_fault_text_names_the_field(text: str, field: str) -> None:
    with pytest.raises(FaultSpecError, match=field):
        parse_fault(text)


def test_schedule_follows_the_clock() -> None:
    clock = FakeClock()
    ctl = FaultController([parse_fault("drop:at=10,for=5")], clock=clock)
    ctl.start()
    assert not ctl.is_active(FaultKind.DROP)
    clock.advance(10.0)
    assert ctl.is_active(FaultKind.DROP)
    clock.advance(5.0)
    assert not ctl.is_active(FaultKind.DROP)


def test_inject_clear_and_one_shot() -> None:
    clock = FakeClock()
    ctl = FaultController(clock=clock)
    f = ctl.inject(FaultKind.COUNTER_GAP, for_s=1.0)
    assert ctl.take_once(FaultKind.COUNTER_GAP) is f
    assert ctl.take_once(FaultKind.COUNTER_GAP) is None
    clock.advance(1.0)
    assert ctl.active() == ()
    g = ctl.inject(FaultKind.HANG)
    sig = ctl.signature()
    assert ctl.clear(g) == 1 and ctl.signature() != sig


def test_channel_faults_apply_to_copies() -> None:
    ctl = FaultController(clock=FakeClock())
    temps = np.arange(4, dtype=float) + 20.0
    status = np.zeros(4, dtype=np.int64)
    ctl.inject(FaultKind.OPEN_CIRCUIT, channels=(1,))
    ctl.inject(FaultKind.OUT_OF_RANGE, channels=(2,), value=500.0)
    ctl.inject(FaultKind.NAN, channels=(3, 99))
    ctl.inject(FaultKind.STUCK, channels=(4,))
    t1, s1 = apply_channel_faults(temps, status, ctl)
    t2, _ = apply_channel_faults(temps + 5.0, status, ctl)
    assert list(s1) == [1, 2, 0, 0] and not status.any()
    assert t1[1] == 500.0 and math.isnan(t1[2])
    assert t2[3] == t1[3] == 23.0 and t2[0] == 25.0
