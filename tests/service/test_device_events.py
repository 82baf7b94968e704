"""Device-state events: on recovery the stored detail says the error was cleared, not that it is current."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta

from drivers.base import SourceMetrics
from service.acquire.devicewatch import DeviceWatch, transition_detail
from service.contracts.health import DeviceHealth, DeviceStatus
from tests.engine_config import product_core


def test_recovery_names_the_cleared_error() -> None:
    detail = transition_detail(DeviceStatus.OK, "modbus 127.0.0.1:5020: cannot connect")
    assert detail == "recovered (last error: modbus 127.0.0.1:5020: cannot connect)"


def test_other_transitions_keep_the_current_message() -> None:
    assert transition_detail(DeviceStatus.DOWN, "cannot connect") == "cannot connect"
    assert transition_detail(DeviceStatus.DEGRADED, "2 channels open") == "2 channels open"
    assert transition_detail(DeviceStatus.OK, "") == ""


# --- transitions from health observations (service.acquire.devicewatch)
# ------------------------------------------


def _dev(status: DeviceStatus, message: str = "", name: str = "modbus") -> DeviceHealth:
    return DeviceHealth(name=name, status=status, last_ok_at=None, age_s=None, counters={}, message=message)


def test_a_device_down_from_the_start_is_reported_once_with_its_reason() -> None:
    """Before, an unreachable DAQ at start-up logged nothing: there was no earlier state to change from."""
    watch = DeviceWatch()
    assert watch.observe([_dev(DeviceStatus.DOWN)]) == []  # not tried yet: no reason to give
    events = watch.observe([_dev(DeviceStatus.DOWN, "modbus 127.0.0.1:5020: cannot connect")])
    assert [(e.device, e.kind, e.detail) for e in events] == [
        ("modbus", "down", "at start-up: modbus 127.0.0.1:5020: cannot connect")
    ]
    assert watch.observe([_dev(DeviceStatus.DOWN, "modbus 127.0.0.1:5020: cannot connect")] * 1) == []
    back = watch.observe([_dev(DeviceStatus.OK)])
    assert [(e.kind, e.detail) for e in back] == [
        ("down->ok", "recovered (last error: modbus 127.0.0.1:5020: cannot connect)")
    ]
    assert watch.observe([_dev(DeviceStatus.OK)]) == []
    again = watch.observe([_dev(DeviceStatus.DOWN, "timeout")])
    assert [(e.kind, e.detail) for e in again] == [("ok->down", "timeout")]


def test_a_silent_device_is_judged_after_the_patience() -> None:
    watch = DeviceWatch(patience=3)
    assert watch.observe([_dev(DeviceStatus.DOWN, name="db")]) == []
    assert watch.observe([_dev(DeviceStatus.DOWN, name="db")]) == []
    assert [e.kind for e in watch.observe([_dev(DeviceStatus.DOWN, name="db")])] == ["down"]


def test_healthy_devices_at_start_up_log_nothing() -> None:
    watch = DeviceWatch()
    assert watch.observe([_dev(DeviceStatus.OK), _dev(DeviceStatus.DISABLED, name="db")]) == []


class _Source:
    """What the service reads of a driver: metrics, connected, is_stale()."""

    def __init__(self) -> None:
        self.metrics = SourceMetrics()
        self.connected = True

    def is_stale(self) -> bool:
        return False

    def condition(self) -> str:
        return ""


def test_a_recovered_device_no_longer_shows_its_old_error(loaded_model) -> None:
    from service.core.machine import ServiceCore
    from service.shell.service import SoftSensorService

    now = [datetime(2026, 3, 2, 6, 0, tzinfo=UTC)]
    src = _Source()
    src.metrics.count_error(TimeoutError("modbus 127.0.0.1:5020: no answer within 1 s"), now[0])
    core = ServiceCore(product_core(), model=loaded_model)
    svc = SoftSensorService(core, worker=None, sources={"modbus": src}, clock=lambda: now[0])
    dev = next(d for d in svc.health().devices if d.name == "modbus")
    assert dev.status is DeviceStatus.DEGRADED and "no answer" in dev.message
    now[0] += timedelta(minutes=5)  # reads fine since: the error is old
    dev = next(d for d in svc.health().devices if d.name == "modbus")
    assert dev.status is DeviceStatus.OK and dev.message == ""
