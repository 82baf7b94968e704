"""Helpers for the simulator tests: a hand-stepped clock, deadline polling, small timelines."""

from __future__ import annotations

import asyncio
import time
from collections.abc import Awaitable, Callable
from typing import TypeVar

import numpy as np

from drivers.sim.source import ArrayTimeline

T = TypeVar("T")


class FakeClock:
    """A monotonic clock that only moves when told to (seconds)."""

    def __init__(self, t: float = 1000.0) -> None:
        self.t = t

    def __call__(self) -> float:
        return self.t

    def advance(self, dt: float) -> None:
        self.t += dt


async def wait_for(
    check: Callable[[], Awaitable[T | None]], *, timeout: float = 5.0, every: float = 0.01
) -> T:
    """Await ``check()`` until it returns something truthy, or fail after ``timeout`` seconds."""
    deadline = time.monotonic() + timeout
    while True:
        result = await check()
        if result:
            return result
        if time.monotonic() > deadline:
            raise AssertionError(f"condition not met within {timeout} s")
        await asyncio.sleep(every)


def ramp_timeline(n_channels: int = 32, duration_s: float = 100.0) -> ArrayTimeline:
    """Two rows 100 s apart: channel k 20 + 0.5 k -> 30 + 0.5 k °C, 1000 -> 5000 rpm, 1 -> 9 N·m."""
    base = 20.0 + 0.5 * np.arange(n_channels)
    status = np.zeros((2, n_channels), dtype=np.int64)
    return ArrayTimeline(
        times_s=np.array([0.0, duration_s]),
        temps_c=np.vstack([base, base + 10.0]),
        ambient_c=np.array([21.0, 23.0]),
        speed_rpm=np.array([1000.0, 5000.0]),
        torque_nm=np.array([1.0, 9.0]),
        status=status,
    )
