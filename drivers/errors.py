"""Typed errors of the acquisition layer.

Third-party errors (pymodbus, python-can, cantools) are translated into this tree exactly once, in the
driver or codec that calls the library, with ``raise ... from err``. Every message names the device,
register range, frame or configuration entry at fault.

::

    DriverError(Exception)
    ├── ConfigError(DriverError, ValueError)            bad register map / DBC / setting; names entry
    ├── EncodeError(DriverError, ValueError)            a value that does not fit its register or signal
    ├── NoDataError(DriverError, LookupError)           nothing acquired yet / empty window
    ├── SampleOrderError(DriverError, ValueError)       sample older than the newest one in a ring buffer
    ├── LogFormatError(DriverError, ValueError)         (drivers.logs) a recorded log that cannot be read
    ├── FaultSpecError(DriverError, ValueError)         (drivers.sim.faults) a bad simulated-fault spec
    ├── TimelineError(DriverError, ValueError)          (drivers.sim.source) a bad simulator timeline
    └── DeviceError(DriverError)                        anything the device (or the link to it) did
        ├── DeviceTimeoutError(DeviceError, TimeoutError)       no answer within the timeout
        ├── DeviceUnavailableError(DeviceError, ConnectionError) cannot connect / connection lost
        └── ProtocolError(DeviceError)                  an answer that is not a valid reply
            ├── ModbusExceptionError(ProtocolError)     Modbus exception response (.exception_code)
            ├── ShortReplyError(ProtocolError)          fewer registers than asked (.start, .count, .got)
            ├── ReplyMismatchError(ProtocolError)       reply's function code / unit id / transaction id
            │                                           differs from the request's (.field, .expected, .got)
            └── FrameError(ProtocolError)               bad CAN frame (.arbitration_id, .dlc)
                ├── UnknownFrameIdError(FrameError)     ID not in the DBC
                ├── WrongDlcError(FrameError)           DLC differs from the DBC (.expected_dlc)
                ├── CounterGapError(FrameError)         rolling counter skipped (.expected, .got)
                └── BadSignalError(FrameError)          undecodable payload / status byte not 0, 1, 2
"""

from __future__ import annotations

MODBUS_EXCEPTION_NAMES: dict[int, str] = {
    1: "illegal function",
    2: "illegal data address",
    3: "illegal data value",
    4: "server device failure",
    5: "acknowledge",
    6: "server device busy",
    8: "memory parity error",
    10: "gateway path unavailable",
    11: "gateway target device failed to respond",
}


class DriverError(Exception):
    """Base of every error raised by ``drivers/``."""


class ConfigError(DriverError, ValueError):
    """A configuration entry (register map, DBC, driver setting) is invalid; the message names it."""

    def __init__(self, message: str, *, entry: str | None = None) -> None:
        super().__init__(f"{entry}: {message}" if entry else message)
        self.entry = entry


class EncodeError(DriverError, ValueError):
    """A value cannot be represented in its register or CAN signal; the message names which."""


class NoDataError(DriverError, LookupError):
    """No sample has been acquired yet, or a requested window holds no data."""


class SampleOrderError(DriverError, ValueError):
    """A sample's timestamp is earlier than the newest one already stored (ring buffers are time-ordered)."""


class DeviceError(DriverError):
    """A device misbehaved or could not be reached. ``device`` names it (e.g. ``modbus 127.0.0.1:5020``)."""

    def __init__(self, message: str, *, device: str = "") -> None:
        super().__init__(f"{device}: {message}" if device else message)
        self.device = device


class DeviceTimeoutError(DeviceError, TimeoutError):
    """The device did not answer within the driver timeout."""


class DeviceUnavailableError(DeviceError, ConnectionError):
    """The device cannot be connected to, or the connection was lost."""


class ProtocolError(DeviceError):
    """The device answered, but the answer is not a valid reply to the request."""


class ModbusExceptionError(ProtocolError):
    """The Modbus server returned an exception response (function code | 0x80)."""

    def __init__(
        self, *, function_code: int, exception_code: int, start: int, count: int, device: str = ""
    ) -> None:
        name = MODBUS_EXCEPTION_NAMES.get(exception_code, "unknown exception")
        super().__init__(
            f"Modbus exception {exception_code} ({name}) for FC{function_code} "
            f"registers {start}-{start + count - 1}",
            device=device,
        )
        self.function_code = function_code
        self.exception_code = exception_code
        self.start = start
        self.count = count


class ShortReplyError(ProtocolError):
    """The reply held fewer (or more) registers than requested, or was garbled."""

    def __init__(self, *, start: int, count: int, got: int, device: str = "", detail: str = "") -> None:
        extra = f" ({detail})" if detail else ""
        super().__init__(
            f"short reply for registers {start}-{start + count - 1}: "
            f"expected {count} registers, got {got}{extra}",
            device=device,
        )
        self.start = start
        self.count = count
        self.got = got


class ReplyMismatchError(ProtocolError):
    """A Modbus reply whose header does not belong to the request: ``field`` is ``"function code"``,
    ``"unit id"`` or ``"transaction id"``; ``expected`` is the request's value, ``got`` the reply's."""

    def __init__(
        self, *, field: str, expected: int, got: int, start: int, count: int, device: str = ""
    ) -> None:
        super().__init__(
            f"reply for registers {start}-{start + count - 1} has {field} {got}, expected {expected}",
            device=device,
        )
        self.field = field
        self.expected = expected
        self.got = got
        self.start = start
        self.count = count


class FrameError(ProtocolError):
    """A CAN frame could not be accepted. Names the arbitration ID and DLC."""

    def __init__(self, message: str, *, arbitration_id: int, dlc: int, device: str = "") -> None:
        super().__init__(f"frame 0x{arbitration_id:03X} (DLC {dlc}): {message}", device=device)
        self.arbitration_id = arbitration_id
        self.dlc = dlc


class UnknownFrameIdError(FrameError):
    """The arbitration ID is not described by the DBC."""


class WrongDlcError(FrameError):
    """The frame length differs from the DBC message length."""

    def __init__(self, *, arbitration_id: int, dlc: int, expected_dlc: int, device: str = "") -> None:
        super().__init__(
            f"wrong DLC, expected {expected_dlc}", arbitration_id=arbitration_id, dlc=dlc, device=device
        )
        self.expected_dlc = expected_dlc


class CounterGapError(FrameError):
    """The 4-bit rolling counter skipped values (frames were lost) or repeated."""

    def __init__(self, *, arbitration_id: int, dlc: int, expected: int, got: int, device: str = "") -> None:
        super().__init__(
            f"rolling counter gap: expected {expected}, got {got}",
            arbitration_id=arbitration_id,
            dlc=dlc,
            device=device,
        )
        self.expected = expected
        self.got = got


class BadSignalError(FrameError):
    """The payload cannot be decoded, or a signal holds a value outside its defined set."""
