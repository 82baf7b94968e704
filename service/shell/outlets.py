"""The outlets subscribed to the running service (``service.serve.outlet``: REST, OPC UA, MQTT): each newly
published view's reader is handed to every outlet's ``on_view`` on the event loop, coalesced and at most every
``interval_s`` (the newest view)."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import time
from collections.abc import Callable
from typing import TYPE_CHECKING

from service.contracts.metrics import OutletMetrics
from service.serve.interface import CountedOutlet
from service.serve.reader import ViewReader

if TYPE_CHECKING:
    from service.serve.outlet import Outlet

__all__ = ["OutletHub"]

log = logging.getLogger(__name__)


class OutletHub:
    """See the module docstring. ``reader()`` gives the newest view's reader; ``loop()`` the running loop
    (None before ``start()``); ``closed()`` stops the deliveries."""

    def __init__(
        self,
        reader: Callable[[], ViewReader],
        loop: Callable[[], asyncio.AbstractEventLoop | None],
        closed: Callable[[], bool],
        interval_s: float = 0.1,
    ) -> None:
        self._reader = reader
        self._loop = loop
        self._closed = closed
        self.interval_s = float(interval_s)
        self.outlets: list[Outlet] = []
        self._pending = False
        self._notified_mono = -math.inf

    def subscribe(self, outlet: Outlet) -> None:
        """Hand every newly published view to ``outlet.on_view`` from now on: on the event loop, coalesced and
        at most every ``interval_s`` (the newest view; see ``service.serve.outlet``). The current view is
        delivered at once (with a running loop; else from the service's ``start()``)."""
        self.outlets.append(outlet)
        self.schedule()

    def unsubscribe(self, outlet: Outlet) -> None:
        with contextlib.suppress(ValueError):
            self.outlets.remove(outlet)

    def schedule(self) -> None:
        """Called by whichever thread published: one delivery pending at a time (a later publish finds it and
        is delivered by it, since the delivery reads the newest view when it runs)."""
        loop = self._loop()
        if not self.outlets or self._pending or loop is None or not loop.is_running():
            return
        self._pending = True
        loop.call_soon_threadsafe(self._notify)

    def _notify(self) -> None:
        loop = self._loop()
        wait = self.interval_s - (time.monotonic() - self._notified_mono)
        if wait > 0 and loop is not None:
            loop.call_later(wait, self._notify)  # still pending: publishes meanwhile coalesce here
            return
        self._pending = False  # before reading the view: a publish from now on schedules anew
        self._notified_mono = time.monotonic()
        if self._closed():
            return
        reader = self._reader()
        for outlet in list(self.outlets):
            try:
                outlet.on_view(reader)
            except Exception as err:  # one outlet's bug must not stop the others nor the service
                log.warning("outlet %s: on_view failed: %s: %s", outlet.name, type(err).__name__, err)

    def metrics(self) -> dict[str, OutletMetrics]:
        """The counters of the outlets that count (``CountedOutlet``), by name."""
        return {o.name: o.outlet_metrics() for o in self.outlets if isinstance(o, CountedOutlet)}
