"""Simulated devices apart from the service: their own event loop in their own thread (``chtc demo``).

Real devices run beside the soft sensor, not inside its event loop: a busy service must not starve them (issue
30: with the devices on the service's loop, a stalled loop made the simulated DAQ miss its polls, the drivers
time out and identifications end ``insufficient-data``). :class:`RigThread` runs the rig's coroutines
(``service.sim.simrig.plant_rig``: the Modbus server and the CAN node) on a loop of its own, in a thread
named ``chtc-rig``. The service reaches it only through the network (Modbus TCP on loopback) and the virtual
CAN channel, as it would a real DAQ and sensor. A thread, not a process: python-can's ``virtual`` channel
lives in one process. The GIL is still shared; the service's heavy work (the Kalman update, the growth
terms) runs in its own threads and releases it in numpy's and SciPy's solvers.

Errors::

    RigThreadError(ServiceError, RuntimeError)   the rig's loop has stopped
"""

from __future__ import annotations

import asyncio
import threading
from collections.abc import Coroutine
from typing import TypeVar

from service.errors import ServiceError

__all__ = ["RigThread", "RigThreadError"]

T = TypeVar("T")


class RigThreadError(ServiceError, RuntimeError):
    """The rig's event loop is not running."""


class RigThread:
    """An event loop in a thread of its own for simulated devices. ``await run(coro)`` from another loop;
    ``close()`` at the end (after the devices stopped)."""

    def __init__(self, name: str = "chtc-rig") -> None:
        self.loop = asyncio.new_event_loop()
        self.thread = threading.Thread(target=self.loop.run_forever, name=name, daemon=True)
        self.thread.start()

    async def run(self, coro: Coroutine[object, object, T]) -> T:
        """Run ``coro`` on the rig's loop and wait for it without blocking the caller's loop."""
        if not self.thread.is_alive() or self.loop.is_closed():
            coro.close()
            raise RigThreadError("the rig's event loop has stopped")
        return await asyncio.wrap_future(asyncio.run_coroutine_threadsafe(coro, self.loop))

    def close(self, timeout_s: float = 10.0) -> None:
        if self.loop.is_closed():
            return
        self.loop.call_soon_threadsafe(self.loop.stop)
        self.thread.join(timeout_s)
        if not self.thread.is_alive():
            self.loop.close()
