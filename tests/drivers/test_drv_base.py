"""Source base class: backoff bounds, reconnect bookkeeping, timeout translation, run loop, stuck detector."""

from __future__ import annotations

import asyncio
import contextlib
import random

import numpy as np
import pytest

from drivers.base import Backoff, Source, StuckDetector
from drivers.errors import DeviceTimeoutError, DeviceUnavailableError, NoDataError, ProtocolError

from .drvhelpers import FakeClock


def test_backoff_grows_is_capped_and_jittered_within_bounds() -> None:
    b = Backoff(initial_s=0.1, factor=2.0, max_s=2.0, jitter=0.25)
    rng = random.Random(1)
    for attempt in range(1, 30):
        base = min(2.0, 0.1 * 2.0 ** (attempt - 1))
        d = b.delay_s(attempt, rng)
        assert 0.75 * base <= d <= base <= 2.0
    assert Backoff(jitter=0.0).delay_s(50, rng) == 2.0
    draws = {round(b.delay_s(10, rng), 6) for _ in range(20)}
    assert len(draws) > 1  # jitter really varies


class Scripted(Source[int]):
    """A source whose connect/read outcomes come from lists (True/int = success, Exception = raise)."""

    def __init__(self, connects: list[object], reads: list[object], **kw: object) -> None:
        super().__init__(name="scripted", **kw)  # type: ignore[arg-type]
        self.connects, self.reads = connects, reads
        self.connect_calls = self.disconnect_calls = 0

    async def _connect(self) -> None:
        self.connect_calls += 1
        outcome = self.connects.pop(0)
        if isinstance(outcome, Exception):
            raise outcome

    async def _read_internal(self) -> int:
        outcome = self.reads.pop(0)
        if isinstance(outcome, Exception):
            raise outcome
        if outcome == "hang":
            await asyncio.sleep(10)
        return int(outcome)  # type: ignore[call-overload]

    async def _disconnect(self) -> None:
        self.disconnect_calls += 1


def test_reconnect_only_when_backoff_due_and_counts() -> None:
    clock = FakeClock()
    down = DeviceUnavailableError("refused")
    src = Scripted(
        [down, down, True, True],
        [1, DeviceTimeoutError("slow"), 2],
        clock=clock,
        backoff=Backoff(initial_s=1.0, factor=2.0, max_s=2.0, jitter=0.0),
        rng=random.Random(0),
    )

    async def main() -> None:
        with pytest.raises(NoDataError):
            src.latest()
        with pytest.raises(DeviceUnavailableError, match="refused"):
            await src.read()
        assert src.retry_in_s() == 1.0
        with pytest.raises(DeviceUnavailableError, match=r"reconnect .* in 1\.00 s"):
            await src.read()
        assert src.connect_calls == 1  # not retried before due
        clock.advance(1.0)
        with pytest.raises(DeviceUnavailableError, match="refused"):
            await src.read()
        assert src.retry_in_s() == 2.0  # second failure doubles the delay
        clock.advance(2.0)
        assert await src.read() == 1 and src.connected and src.metrics.reconnects == 0
        with pytest.raises(DeviceTimeoutError):
            await src.read()
        assert not src.connected and src.retry_in_s() == 1.0  # success reset the failure count
        clock.advance(1.0)
        assert await src.read() == 2
        assert src.metrics.reconnects == 1 and src.metrics.connects == 2
        assert src.metrics.errors == {"DeviceUnavailableError": 2, "DeviceTimeoutError": 1}
        assert src.metrics.events == {"polls_while_down": 1}
        await src.close()
        with pytest.raises(DeviceUnavailableError, match="closed"):
            await src.read()

    asyncio.run(main())


def test_protocol_error_keeps_link_and_bare_timeout_is_translated() -> None:
    src = Scripted([True], [ProtocolError("bad"), "hang", 5], timeout_s=0.05)

    async def main() -> None:
        async with src:
            with pytest.raises(ProtocolError):
                await src.read()
            assert src.connected
            with pytest.raises(DeviceTimeoutError, match=r"no answer to read within 0\.05 s"):
                await src.read()
            assert not src.connected
        assert src.closed and src.disconnect_calls >= 2

    asyncio.run(main())


def test_run_loop_reports_errors_and_waits_for_backoff() -> None:
    clock = FakeClock()
    waits: list[float] = []
    down = DeviceUnavailableError("refused")

    async def fake_sleep(s: float) -> None:
        waits.append(s)
        clock.advance(s)
        if len(waits) >= 4:
            raise asyncio.CancelledError

    src = Scripted(
        [down, True], [7, 8, 9], clock=clock, sleep=fake_sleep, backoff=Backoff(initial_s=0.5, jitter=0.0)
    )
    got: list[int] = []
    errors: list[Exception] = []

    async def main() -> None:
        with pytest.raises(asyncio.CancelledError):
            await src.run(interval_s=0.1, on_reading=got.append, on_error=errors.append)

    asyncio.run(main())
    assert [type(e) for e in errors] == [DeviceUnavailableError]
    assert waits[0] == pytest.approx(0.5)  # waited for the reconnect, not just the interval
    assert got == [7, 8, 9]
    assert waits[1:] == pytest.approx([0.1, 0.1, 0.1])


class SwallowsCancel(Scripted):
    """A read that eats a cancellation and returns, as pymodbus' client did on shutdown."""

    async def _read_internal(self) -> int:
        with contextlib.suppress(asyncio.CancelledError):
            await asyncio.sleep(10)
        return 1


def test_run_loop_ends_on_cancel_even_when_the_client_swallows_it() -> None:
    src = SwallowsCancel([True], [])

    async def main() -> None:
        task = asyncio.create_task(src.run(interval_s=0.01))
        await asyncio.sleep(0.05)  # the loop is inside the read now
        task.cancel()
        done, _ = await asyncio.wait({task}, timeout=5.0)
        if not done:  # let the loop end so that the failure is reported instead of hanging
            await src.close()
            await asyncio.wait({task}, timeout=15.0)
        assert done, "the run loop kept running after cancel()"
        assert task.cancelled()

    asyncio.run(main())


def test_stale_after_last_good_read() -> None:
    clock = FakeClock()
    src = Scripted([True], [1], clock=clock, stale_after_s=5.0)

    async def main() -> None:
        assert src.is_stale()
        await src.read()
        assert not src.is_stale()
        clock.advance(5.1)
        assert src.is_stale()

    asyncio.run(main())


def test_stuck_detector() -> None:
    d = StuckDetector(3, samples=3, tolerance=0.0)
    seq = [[1.0, np.nan, 5.0], [1.0, np.nan, 5.1], [1.0, np.nan, 5.1], [1.0, np.nan, 5.1], [1.2, np.nan, 5.1]]
    masks = [d.update(np.array(v)).tolist() for v in seq]
    assert masks == [
        [False] * 3,
        [False] * 3,
        [True, False, False],
        [True, False, True],
        [False, False, True],
    ]
    d.reset()
    assert not d.stuck().any()
    with pytest.raises(ValueError):
        StuckDetector(3, samples=1)
