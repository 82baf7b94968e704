"""Plain JSON mode (pure): one retained topic per metric and a retained availability topic::

    {prefix}/{device}/availability            "online" (retained; the Will sets "offline")
    {prefix}/{device}/Status/Usable           {"v": true, "q": "good", "t": "2026-11-27T23:10:00.000Z"}
    {prefix}/{device}/Chtc/H1                 {"v": 41.7, "q": "uncertain", "t": "..."}

The metric names are the Sparkplug ones (``service.serve.mqtt.points.CATALOGUE``) as topic levels; ``v``
is the value (null when absent; a time as UTC ISO-8601), ``q`` ``good`` | ``uncertain`` | ``bad``, ``t``
the data's time (UTC ISO-8601).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from datetime import UTC, datetime

from service.serve.mqtt.points import Point

__all__ = ["OFFLINE", "ONLINE", "JsonTopics", "iso", "payload"]

ONLINE = b"online"
OFFLINE = b"offline"


def iso(t: datetime) -> str:
    """UTC ISO-8601 with milliseconds and a ``Z``."""
    return t.astimezone(UTC).strftime("%Y-%m-%dT%H:%M:%S.") + f"{t.microsecond // 1000:03d}Z"


@dataclass(frozen=True)
class JsonTopics:
    prefix: str
    device: str

    @property
    def availability(self) -> str:
        return f"{self.prefix}/{self.device}/availability"

    def value(self, name: str) -> str:
        return f"{self.prefix}/{self.device}/{name}"


def payload(p: Point) -> bytes:
    v = iso(p.value) if isinstance(p.value, datetime) else p.value
    return json.dumps({"v": v, "q": p.quality.json, "t": iso(p.t)}, ensure_ascii=False).encode()
