"""MQTT for the spindles of a host (``[[spindles]]``, ``service.host.fleet``; issue 43).

Sparkplug B: **one edge node** (``[mqtt] group_id``/``edge_node_id``, one connection, one bdSeq, one Will:
NDEATH) with **one device per running spindle**, named by its id (``spindles[i].id``) unless the entry sets
``mqtt = {device_id = "..."}``::

    NBIRTH  once per connect and per honoured rebirth, then a DBIRTH per running spindle
    DDATA   per spindle, from its own views (the metrics of a single spindle's device)
    DDEATH  a spindle that stops (its feed closed); a spindle whose devices fail keeps its device and shows
            it in its metrics' Quality (stale 500 / bad 0) and Health/*, as a single spindle does
    NCMD    Node Control/Rebirth: NBIRTH and every DBIRTH again

JSON: **one connection per spindle** (each its own retained availability topic and Will, which one connection
could not give several devices), ``{topic_prefix}/{device}/...`` as for a single spindle; a set
``client_id`` gets ``-{device}`` appended so the connections do not take each other's place.

``feeds[spindle id]``: subscribe each to its spindle's service (as ``HostedOpcUa.feeds``).
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable, Mapping
from datetime import datetime
from typing import TYPE_CHECKING

from service.contracts.metrics import OutletMetrics
from service.serve.mqtt.outlet import DeviceFeed, MqttOutlet
from service.settings import default_data_dir

if TYPE_CHECKING:
    from service.settings import Settings

__all__ = ["HostedMqtt"]


class HostedMqtt:
    """See the module docstring. ``spindles``: each running spindle's settings (``Settings.per_spindle()``:
    its ``[mqtt]`` with its own ``device_id`` when set), by id, in the order of the file."""

    name = "mqtt"

    def __init__(
        self,
        settings: Settings,
        spindles: Mapping[str, Settings],
        *,
        clock: Callable[[], datetime],
        on_event: Callable[[str], None],
    ) -> None:
        if not spindles:
            raise ValueError("HostedMqtt: no spindle")
        base = settings.mqtt
        state = base.state_dir if base.state_dir is not None else default_data_dir()
        sections = {sid: s.mqtt.for_spindle(sid) for sid, s in spindles.items()}
        self.devices = {sid: cfg.device for sid, cfg in sections.items()}
        self.outlets: list[MqttOutlet] = []
        self.feeds: dict[str, DeviceFeed] = {}
        if base.mode == "sparkplug":
            first = next(iter(sections.values()))
            node = MqttOutlet(
                first, state_dir=state, clock=clock, on_event=on_event, devices=list(self.devices.values())
            )
            self.outlets.append(node)
            self.feeds = {sid: node.feeds[device] for sid, device in self.devices.items()}
            return
        for sid, cfg in sections.items():
            if cfg.client_id:
                cfg = cfg.model_copy(update={"client_id": f"{cfg.client_id}-{cfg.device}"})
            outlet = MqttOutlet(cfg, state_dir=state, clock=clock, on_event=on_event)
            self.outlets.append(outlet)
            self.feeds[sid] = outlet.feeds[cfg.device]

    async def start(self) -> None:
        for outlet in self.outlets:
            await outlet.start()

    async def close(self) -> None:
        await asyncio.gather(*(o.close() for o in self.outlets), return_exceptions=True)

    def outlet_metrics(self) -> OutletMetrics:
        """The connections' counters summed (``connected``: all of them)."""
        ms = [o.outlet_metrics() for o in self.outlets]
        return OutletMetrics(
            sent=sum(m.sent for m in ms),
            dropped=sum(m.dropped for m in ms),
            buffered=sum(m.buffered for m in ms),
            reconnects=sum(m.reconnects for m in ms),
            connect_failures=sum(m.connect_failures for m in ms),
            connected=all(bool(m.connected) for m in ms),
        )
