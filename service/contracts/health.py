"""The health of the service's devices and of the service (``/health``, ``/ready``): ``DeviceStatus``,
``DeviceHealth`` (judged by ``service.acquire.devicewatch``), ``HealthSnapshot``, ``Readiness``."""

from __future__ import annotations

import enum
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from datetime import datetime

__all__ = ["DeviceHealth", "DeviceStatus", "HealthSnapshot", "Readiness"]


class DeviceStatus(enum.StrEnum):
    OK = "ok"
    DEGRADED = "degraded"  # reachable, but faults/bad channels/retries
    DOWN = "down"
    DISABLED = "disabled"


@dataclass(frozen=True, kw_only=True)
class DeviceHealth:
    name: str  # "modbus" | "can" | "db" | "worker" | "filter"
    status: DeviceStatus
    last_ok_at: datetime | None  # UTC of the last good read/frame/write
    age_s: float | None  # seconds since last_ok_at, at the time of health()
    counters: Mapping[str, int] = field(default_factory=dict)  # e.g. {"polls": 10, "timeouts": 1}
    message: str = ""


@dataclass(frozen=True, kw_only=True)
class HealthSnapshot:
    t: datetime
    devices: Sequence[DeviceHealth]
    model_loaded: bool
    model_version: str | None
    uptime_s: float


@dataclass(frozen=True)
class Readiness:
    ready: bool  # model loaded and data fresh
    reasons: Sequence[str] = ()  # why not, e.g. ("model not loaded", "no sample for 35 s")
