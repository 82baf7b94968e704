"""The outlet seam: how REST, OPC UA and MQTT (and any later outlet) get the service's published values.

Contract (issue 28)::

    shell.publish(CoreView) --(on the event loop, at most every outlet_interval_s)--> outlet.on_view(reader)

- An :class:`Outlet` has a ``name``, ``async start()``, ``on_view(reader)`` and ``async close()``. The runtime
  starts the enabled ones after the service (``SoftSensorService.start()``) and closes them, in reverse
  order, before it.
- ``SoftSensorService.subscribe(outlet)`` registers it. After each published view the shell calls
  ``outlet.on_view(reader)`` **on the event loop** with a :class:`service.serve.reader.ViewReader` of the
  newest view. Publishing can be frequent (one view per sample and per job outcome; at a ``chtc demo``
  speed-up many per second), so the calls are **coalesced and rate-limited**: at most one per
  ``outlet_interval_s`` (``SoftSensorService(outlet_interval_s=...)``, default 0.1 s), always with the
  newest view (intermediate views are skipped, never queued). A view published during the wait is delivered at
  the end
  of it: nothing newer than the last delivery is ever dropped.
- ``on_view`` **must not block** (it runs on the loop that serves REST): keep the reader (immutable, safe to
  read from any thread) or copy what is needed, and hand it to the outlet's own task or thread (e.g. a
  latest-value slot and ``loop.call_soon_threadsafe``). An exception in ``on_view`` is logged and does not
  stop the others.
- The reader answers with the same verdicts as REST (``chtc()``, ``compensation()``, ``sensors()``,
  ``condition()``, ``health()``...): an outlet only renders them. Its ages are taken at the time of the call,
  so re-reading the last reader on a timer shows values going stale when no new view arrives (the
  acquisition stopped).

Outlets are built by an :data:`OutletFactory` ``(OutletContext) -> Outlet``. The runtime looks a name up in
:data:`OUTLETS`, a registry of ``"module:attribute"`` paths resolved when the outlet is enabled (the way
entry points work): ``service`` never imports ``api``, the REST outlet lives in ``api.outlet`` and is found by
name. A test or an embedding application can pass its own factories to ``Runtime(outlets=...)``.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from datetime import datetime
from typing import TYPE_CHECKING, Any, Protocol

from service.serve.errors import OutletError

if TYPE_CHECKING:
    from service.serve.reader import ViewReader
    from service.settings import Settings

__all__ = ["OUTLETS", "Outlet", "OutletContext", "OutletError", "OutletFactory", "load_factory"]


class Outlet(Protocol):
    """One way out of the service (see the module docstring)."""

    name: str

    async def start(self) -> None:
        """Open the outlet (bind the server, connect to the broker); called once on the event loop."""
        ...

    def on_view(self, reader: ViewReader) -> None:
        """A new view was published: called on the event loop; must not block."""
        ...

    async def close(self) -> None:
        """Stop serving and release everything; called once on the event loop."""
        ...


@dataclass(frozen=True, kw_only=True)
class OutletContext:
    """What a factory gets: the settings, the running service (``ChtcService``: reads and writes), the run's
    clock and whether it is a simulated plant time, and the event sink for operator messages."""

    settings: Settings
    service: Any  # service.shell.service.SoftSensorService (typed loosely: serve may not import engine)
    clock: Callable[[], datetime]
    simulated: bool = False
    speedup: float = 1.0
    on_event: Callable[[str], None] = print


OutletFactory = Callable[[OutletContext], Outlet]

# name -> "module:attribute" of its factory; "rest" is always available (the API), the others are enabled in
# their settings section ([opcua] enabled = true, [mqtt] enabled = true)
OUTLETS: Mapping[str, str] = {
    "rest": "api.outlet:rest_outlet",
    "rest_fleet": "api.fleet:fleet_outlet",  # an instance hosting several spindles (service.host.fleet)
    "opcua": "service.serve.opcua.outlet:opcua_outlet",
    "mqtt": "service.serve.mqtt.outlet:mqtt_outlet",
}


def load_factory(name: str, registry: Mapping[str, str] = OUTLETS) -> OutletFactory:
    """The factory registered as ``name``; ``OutletError`` names what is missing."""
    path = registry.get(name)
    if path is None:
        raise OutletError(f"unknown outlet {name!r} (known: {', '.join(sorted(registry))})")
    module, _, attr = path.partition(":")
    try:
        factory = getattr(importlib.import_module(module), attr)
    except (ImportError, AttributeError) as err:
        raise OutletError(f"outlet {name!r}: cannot load {path}: {err}") from err
    return factory
