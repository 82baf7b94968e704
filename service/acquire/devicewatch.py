"""Device-state transitions from periodic health observations (pure; the service's health loop feeds it).

Each observation of a device (``service.contracts.health.DeviceHealth``) is compared with the previous one; a
change
of status is one event ``"<old>-><new>"``, logged and stored once. A device that is already down or degraded
when it is first seen is reported once as ``"down"``/``"degraded"`` ("at start-up"): an unreachable DAQ at
start-up used to log nothing at all, because there was no previous state to change from. A first
observation that is down with no message yet (the driver has not tried to connect) is not judged until it
has a message, or after ``patience`` observations. On recovery the detail names the last error seen while
the device was not ok, now cleared (the health message itself no longer shows it).
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

from service.contracts.health import DeviceHealth, DeviceStatus

__all__ = ["DeviceEvent", "DeviceWatch", "transition_detail"]

_BAD = (DeviceStatus.DOWN, DeviceStatus.DEGRADED)


@dataclass(frozen=True, kw_only=True)
class DeviceEvent:
    device: str
    kind: str  # "down->ok", or "down" for a device first seen not ok
    detail: str


def transition_detail(status: DeviceStatus, message: str) -> str:
    """The detail of a device-state event: on recovery the device's message is its last error, now cleared."""
    if status is DeviceStatus.OK and message:
        return f"recovered (last error: {message})"
    return message


class DeviceWatch:
    """``observe(devices) -> events``; remembers each device's status and its last error message."""

    def __init__(self, *, patience: int = 5) -> None:
        self.patience = patience
        self.state: dict[str, DeviceStatus] = {}
        self._last_error: dict[str, str] = {}
        self._unjudged: dict[str, int] = {}

    def observe(self, devices: Iterable[DeviceHealth]) -> list[DeviceEvent]:
        """The events of this round of observations (at most one per device)."""
        events = (self._one(dev) for dev in devices)
        return [e for e in events if e is not None]

    def _one(self, dev: DeviceHealth) -> DeviceEvent | None:
        if dev.status in _BAD and dev.message:
            self._last_error[dev.name] = dev.message
        prev = self.state.get(dev.name)
        if prev is None:
            return self._first(dev)
        if prev == dev.status:
            return None
        self.state[dev.name] = dev.status
        last = self._last_error.pop(dev.name, "") if dev.status is DeviceStatus.OK else dev.message
        return DeviceEvent(
            device=dev.name,
            kind=f"{prev.value}->{dev.status.value}",
            detail=transition_detail(dev.status, last),
        )

    def _first(self, dev: DeviceHealth) -> DeviceEvent | None:
        if dev.status not in _BAD:
            self.state[dev.name] = dev.status
            return None
        seen = self._unjudged[dev.name] = self._unjudged.get(dev.name, 0) + 1
        if not dev.message and seen < self.patience:
            return None  # not tried yet: judge it when it has a reason
        self.state[dev.name] = dev.status
        detail = f"at start-up: {dev.message}" if dev.message else "at start-up"
        return DeviceEvent(device=dev.name, kind=dev.status.value, detail=detail)
