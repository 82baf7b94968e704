"""Device-state events: on recovery the stored detail says the error was cleared, not that it is current."""

from __future__ import annotations

from service.interface import DeviceStatus
from service.service import transition_detail


def test_recovery_names_the_cleared_error() -> None:
    detail = transition_detail(DeviceStatus.OK, "modbus 127.0.0.1:5020: cannot connect")
    assert detail == "recovered (last error: modbus 127.0.0.1:5020: cannot connect)"


def test_other_transitions_keep_the_current_message() -> None:
    assert transition_detail(DeviceStatus.DOWN, "cannot connect") == "cannot connect"
    assert transition_detail(DeviceStatus.DEGRADED, "2 channels open") == "2 channels open"
    assert transition_detail(DeviceStatus.OK, "") == ""
