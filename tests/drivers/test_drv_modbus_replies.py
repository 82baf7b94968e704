"""Modbus driver against the simulated DAQ on loopback: reply headers are checked, a garbled reply logs one
line without a traceback, the sample counter wraps round, and the unit id comes from one place."""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Awaitable, Callable
from typing import Any

import pytest

from drivers.base import Backoff
from drivers.errors import ConfigError, ModbusExceptionError, ReplyMismatchError, ShortReplyError
from drivers.modbus_daq import ModbusDaq
from drivers.registers import default_register_map
from drivers.sim.faults import FaultController, FaultKind
from drivers.sim.modbus_server import SimulatedDaq
from drivers.sim.source import ArrayTimeline, TimelineSource

from .drvhelpers import FakeClock

FAST = Backoff(initial_s=0.01, max_s=0.02, jitter=0.0)


def _with_sim(
    body: Callable[[SimulatedDaq, FaultController], Awaitable[None]], *, clock: Any = None, **kw: Any
) -> None:
    async def main() -> None:
        faults = FaultController()
        extra = {"clock": clock} if clock is not None else {}
        source = TimelineSource(ArrayTimeline.constant(temps_c=25.0), **extra)
        async with SimulatedDaq(source, port=0, faults=faults, **kw) as sim:
            await body(sim, faults)

    asyncio.run(main())


async def _read_after_backoff(daq: ModbusDaq) -> Any:
    """One read once the reconnect backoff allows it (the link is dropped after a bad reply)."""
    deadline = asyncio.get_running_loop().time() + 5.0
    while daq.retry_in_s() > 0:
        assert asyncio.get_running_loop().time() < deadline, "reconnect never became due"
        await asyncio.sleep(daq.retry_in_s())
    return await daq.read()


@pytest.mark.parametrize(
    ("kind", "value", "field", "got"),
    [
        (FaultKind.WRONG_FC, 3, "function code", 3),
        (FaultKind.WRONG_UNIT, 9, "unit id", 9),
        (FaultKind.WRONG_TID, 5, "transaction id", None),
    ],
)
def test_reply_header_mismatch_is_rejected_counted_and_named(
    kind: FaultKind, value: int, field: str, got: int | None
) -> None:
    async def body(sim: SimulatedDaq, faults: FaultController) -> None:
        async with ModbusDaq("127.0.0.1", sim.port, timeout_s=2.0, backoff=FAST) as daq:
            assert (await daq.read()).temps_c[0] == pytest.approx(25.0)
            fault = faults.inject(kind, value=value)
            started = asyncio.get_running_loop().time()
            for _ in range(3):
                with pytest.raises(ReplyMismatchError) as info:
                    await _read_after_backoff(daq)
                err = info.value
                assert err.field == field and f"has {field}" in str(err)
                assert err.got == (got if got is not None else err.expected + value)
            # rejected at once, not after the 2 s request timeout
            assert asyncio.get_running_loop().time() - started < 2.0
            assert daq.metrics.errors == {"ReplyMismatchError": 3}
            assert daq.metrics.reads_ok == 1
            faults.clear(fault)
            assert (await _read_after_backoff(daq)).temps_c[0] == pytest.approx(25.0)

    _with_sim(body)


def test_garbled_reply_logs_one_line_per_distinct_error_without_traceback(
    caplog: pytest.LogCaptureFixture,
) -> None:
    caplog.set_level(logging.DEBUG)

    async def body(sim: SimulatedDaq, faults: FaultController) -> None:
        async with ModbusDaq("127.0.0.1", sim.port, timeout_s=1.0, backoff=FAST) as daq:
            await daq.read()
            faults.inject(FaultKind.GARBLED, value=2)  # byte count claims 4 bytes more than sent
            for _ in range(5):
                with pytest.raises(ShortReplyError, match="byte count 70 but 66 data bytes"):
                    await _read_after_backoff(daq)
            faults.clear()
            faults.inject(FaultKind.WRONG_FC, value=3)
            for _ in range(3):
                with pytest.raises(ReplyMismatchError):
                    await _read_after_backoff(daq)

    _with_sim(body)
    warnings = [r for r in caplog.records if r.levelno >= logging.WARNING]
    assert [r.name for r in warnings] == ["drivers", "drivers"], [r.getMessage() for r in warnings]
    assert "byte count 70 but 66 data bytes" in warnings[0].getMessage()
    assert "function code 3, expected 4" in warnings[1].getMessage()
    assert all(r.exc_info is None and "\n" not in r.getMessage() for r in warnings)


def test_error_log_reports_repeats_once_the_interval_has_passed(caplog: pytest.LogCaptureFixture) -> None:
    from drivers.base import ErrorLog

    clock = FakeClock()
    log = ErrorLog(logging.getLogger("drivers"), every_s=60.0, clock=clock)
    caplog.set_level(logging.WARNING, logger="drivers")
    err = ShortReplyError(start=0, count=33, got=0, detail="garbled reply, 75 bytes")
    assert log.error(err)
    assert not log.error(ShortReplyError(start=100, count=33, got=0, detail="garbled reply, 75 bytes"))
    clock.advance(61.0)
    assert log.error(err)
    assert "(repeated 1 times in 61 s)" in caplog.records[-1].getMessage()
    assert len(caplog.records) == 2


def test_counter_wrap_is_a_new_sample_not_a_restart() -> None:
    clock = FakeClock()

    async def body(sim: SimulatedDaq, faults: FaultController) -> None:
        async with ModbusDaq("127.0.0.1", sim.port, timeout_s=1.0, stale_after_s=100.0, clock=clock) as daq:
            counters, news = [], []
            for _ in range(4):
                r = await daq.read()
                counters.append(r.counter)
                news.append(r.new_sample and not r.restarted)
                clock.advance(0.1)  # one simulated DAQ sample
            assert counters == [0xFFFFFFFE, 0xFFFFFFFF, 0, 1]
            assert news == [True, True, True, True]
            assert "restarts" not in daq.metrics.events
            assert daq.metrics.events["new_samples"] == 4

    _with_sim(body, clock=clock, counter_start=0xFFFFFFFE)


def test_counter_going_back_is_still_a_restart() -> None:
    clock = FakeClock()

    async def body(sim: SimulatedDaq, faults: FaultController) -> None:
        async with ModbusDaq("127.0.0.1", sim.port, timeout_s=1.0, stale_after_s=100.0, clock=clock) as daq:
            clock.advance(0.5)
            assert (await daq.read()).counter == 5
            sim.counter_start = -6  # the DAQ restarts: its next sample is counted 0
            clock.advance(0.1)
            r = await daq.read()
            assert r.counter == 0 and r.restarted
            assert daq.metrics.events["restarts"] == 1

    _with_sim(body, clock=clock)


def test_unit_id_setting_overrides_the_map_and_is_validated() -> None:
    async def body(sim: SimulatedDaq, faults: FaultController) -> None:
        async with ModbusDaq("127.0.0.1", sim.port, timeout_s=1.0, unit_id=7) as daq:
            assert daq.unit_id == 7
            assert (await daq.read()).temps_c[0] == pytest.approx(25.0)
        # without the override the map's unit id (1) is asked for; this device only knows unit 7
        async with ModbusDaq("127.0.0.1", sim.port, timeout_s=0.3) as daq:
            assert daq.unit_id == 1
            with pytest.raises(ModbusExceptionError):
                await daq.read()

    _with_sim(body, register_map=default_register_map(unit_id=7))
    for bad in (-1, 248, 255):
        with pytest.raises(ConfigError, match=f"modbus.unit: unit id {bad} outside 0..247"):
            ModbusDaq(unit_id=bad)
