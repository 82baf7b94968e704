"""Fault injection for the simulated DAQ and CAN node: a schedule plus a controller tests and the CLI drive.

A :class:`Fault` is a kind, optional channels (1-based), a start ``at_s`` and a length ``for_s`` in *wall*
seconds after the controller started (``None``: until cleared), and an optional ``value`` whose meaning
depends on the kind (see :class:`FaultKind`). Faults are scheduled up front or injected/cleared at run time::

    faults = FaultController([parse_fault("drop:at=30,for=10")])
    f = faults.inject(FaultKind.OPEN_CIRCUIT, channels=(5,))
    faults.clear(f)

The simulators ask the controller what is active whenever they answer or send (no background timers), so a
test that injects a fault sees it at the next request. The clock is injected (default ``time.monotonic``).

Text form (CLI ``--fault``): ``KIND[:key=value,...]`` with keys ``ch`` (channels joined by ``+``), ``at``,
``for`` (s) and ``value`` (aliases ``code``, ``n``, ``id``, ``dlc``), e.g. ``open:ch=5+6,at=10,for=20``,
``exception:code=4``, ``counter-gap:n=3``, ``unknown-id:id=0x7E0``.

Errors: :class:`FaultSpecError` (``ValueError``) names the bad field of a fault text.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from enum import StrEnum

import numpy as np
from numpy.typing import NDArray

from drivers.errors import DriverError

__all__ = [
    "CHANNEL_FAULTS",
    "Fault",
    "FaultController",
    "FaultKind",
    "FaultSpecError",
    "apply_channel_faults",
    "parse_fault",
]


class FaultKind(StrEnum):
    """What goes wrong, and what ``Fault.value`` means for it."""

    OPEN_CIRCUIT = "open"  # DAQ status 1 on the channels (value: temperature reported, default unchanged)
    STUCK = "stuck"  # channel value frozen at the value it had when the fault began (value: fixed °C)
    OUT_OF_RANGE = "range"  # DAQ status 2 and an implausible value (value: °C, default 327.0)
    NAN = "nan"  # channel reads "no value" (int16 0x8000 / float32 NaN)
    FREEZE = "freeze"  # DAQ stops sampling: counter and all values stop changing
    HANG = "hang"  # Modbus requests are accepted but not answered (client times out)
    DROP = "drop"  # Modbus connections dropped and new ones refused (device off / restarting)
    GARBLED = "garbled"  # Modbus reply cut in half (value 2: byte count does not match the data)
    SHORT = "short"  # Modbus reply with fewer registers than requested (value: registers missing, default 1)
    EXCEPTION = "exception"  # Modbus exception response (value: exception code, default 4 device failure)
    COUNTER_GAP = (
        "counter-gap"  # CAN rolling counter skips once per activation (value: frames lost, default 3)
    )
    UNKNOWN_ID = "unknown-id"  # extra CAN frames with an ID not in the DBC (value: ID, default 0x7E0)
    WRONG_DLC = "wrong-dlc"  # SpindleStatus sent with the wrong length (value: DLC, default 4)
    FAULT_STATUS = "fault-status"  # SpindleStatus status byte 2 (fault) (value: status byte)
    SILENCE = "silence"  # the CAN node sends nothing
    WRONG_FC = "wrong-fc"  # Modbus reply carries another function code (value: FC, default 3)
    WRONG_UNIT = "wrong-unit"  # Modbus reply carries another unit id (value: unit id, default 99)
    WRONG_TID = "wrong-tid"  # Modbus reply carries another transaction id (value: added to it, default 1)
    FD_FRAME = "fd"  # SpindleStatus sent as a CAN FD frame (the contract is CAN 2.0A)
    EXTENDED_ID = "extended-id"  # SpindleStatus sent with a 29-bit (extended) ID 0x181
    REMOTE_FRAME = "remote"  # a remote (RTR) frame with ID 0x181 added each period


CHANNEL_FAULTS: frozenset[FaultKind] = frozenset(
    {FaultKind.OPEN_CIRCUIT, FaultKind.STUCK, FaultKind.OUT_OF_RANGE, FaultKind.NAN}
)
DEFAULT_VALUES: dict[FaultKind, float] = {
    FaultKind.OUT_OF_RANGE: 327.0,
    FaultKind.SHORT: 1,
    FaultKind.EXCEPTION: 4,
    FaultKind.COUNTER_GAP: 3,
    FaultKind.UNKNOWN_ID: 0x7E0,
    FaultKind.WRONG_DLC: 4,
    FaultKind.FAULT_STATUS: 2,
    FaultKind.WRONG_FC: 3,
    FaultKind.WRONG_UNIT: 99,
    FaultKind.WRONG_TID: 1,
}


class FaultSpecError(DriverError, ValueError):
    """A fault description is invalid; the message names the field."""


@dataclass(frozen=True)
class Fault:
    """One fault: ``kind``, ``channels`` (1-based), start ``at_s``, length ``for_s`` (wall s), ``value``."""

    kind: FaultKind
    channels: tuple[int, ...] = ()
    at_s: float = 0.0
    for_s: float | None = None
    value: float | None = None

    def __post_init__(self) -> None:
        if self.kind in CHANNEL_FAULTS and not self.channels:
            raise FaultSpecError(f"{self.kind}: ch (channels) is required")
        if any(c < 1 for c in self.channels):
            raise FaultSpecError(f"{self.kind}: ch must be >= 1, got {self.channels}")
        if self.for_s is not None and not self.for_s > 0:
            raise FaultSpecError(f"{self.kind}: for must be > 0, got {self.for_s}")
        if not math.isfinite(self.at_s) or self.at_s < 0:
            raise FaultSpecError(f"{self.kind}: at must be >= 0, got {self.at_s}")

    def __str__(self) -> str:
        chans = f" ch={'+'.join(map(str, self.channels))}" if self.channels else ""
        value = f" value={self.value:g}" if self.value is not None else ""
        until = f"for {self.for_s:g} s" if self.for_s is not None else "until cleared"
        return f"{self.kind.value}{chans}{value} from {self.at_s:g} s {until}"

    def param(self) -> float:
        """``value`` or the kind's default (NaN when the kind has none)."""
        return self.value if self.value is not None else DEFAULT_VALUES.get(self.kind, math.nan)

    def active_at(self, t_s: float) -> bool:
        """Whether the fault is on at ``t_s`` wall seconds after the controller started."""
        return self.at_s <= t_s and (self.for_s is None or t_s < self.at_s + self.for_s)


_VALUE_ALIASES = ("value", "code", "n", "id", "dlc", "status")


def parse_fault(text: str) -> Fault:
    """Parse ``KIND[:key=value,...]`` (see the module docstring) into a :class:`Fault`."""
    kind_text, _, rest = text.strip().partition(":")
    try:
        kind = FaultKind(kind_text.strip().lower())
    except ValueError as err:
        kinds = ", ".join(k.value for k in FaultKind)
        raise FaultSpecError(f"fault kind {kind_text!r} unknown (one of {kinds})") from err
    fields: dict[str, str] = {}
    for part in filter(None, (p.strip() for p in rest.split(","))):
        key, sep, val = part.partition("=")
        if not sep:
            raise FaultSpecError(f"{kind}: {part!r} is not key=value")
        fields[key.strip().lower()] = val.strip()
    return Fault(
        kind=kind,
        channels=_channels(kind, fields.pop("ch", "")),
        at_s=_number(kind, "at", fields.pop("at", "0")),
        for_s=_number(kind, "for", fields["for"]) if "for" in fields else None,
        value=_value(kind, fields),
    )


def _channels(kind: FaultKind, text: str) -> tuple[int, ...]:
    try:
        return tuple(int(c) for c in text.split("+") if c.strip())
    except ValueError as err:
        raise FaultSpecError(f"{kind}: ch must be integers joined by '+', got {text!r}") from err


def _number(kind: FaultKind, key: str, text: str) -> float:
    try:
        return float(int(text, 0)) if text.lower().startswith("0x") else float(text)
    except ValueError as err:
        raise FaultSpecError(f"{kind}: {key} must be a number, got {text!r}") from err


def _value(kind: FaultKind, fields: dict[str, str]) -> float | None:
    found = [k for k in fields if k in _VALUE_ALIASES]
    unknown = [k for k in fields if k not in _VALUE_ALIASES and k != "for"]
    if unknown:
        raise FaultSpecError(f"{kind}: unknown key(s) {unknown}")
    return _number(kind, found[0], fields[found[0]]) if found else None


@dataclass
class _Entry:
    fault: Fault
    ident: int
    consumed: bool = False
    memory: dict[int, float] = field(default_factory=dict)


class FaultController:
    """The active set of faults; thread-safe enough for one asyncio loop plus reads from other threads."""

    def __init__(
        self, schedule: Iterable[Fault] = (), *, clock: Callable[[], float] = time.monotonic
    ) -> None:
        self.clock = clock
        self._t0: float | None = None
        self._entries: list[_Entry] = []
        self._next_id = 0
        for f in schedule:
            self._add(f)

    def _add(self, fault: Fault) -> _Entry:
        entry = _Entry(fault, self._next_id)
        self._next_id += 1
        self._entries.append(entry)
        return entry

    def start(self) -> None:
        """Fix the origin of ``at_s`` (called by the first simulator that starts, if not before)."""
        if self._t0 is None:
            self._t0 = self.clock()

    def elapsed_s(self) -> float:
        """Wall seconds since :meth:`start`."""
        self.start()
        assert self._t0 is not None
        return self.clock() - self._t0

    def inject(
        self,
        kind: FaultKind | str,
        *,
        channels: Iterable[int] = (),
        for_s: float | None = None,
        value: float | None = None,
    ) -> Fault:
        """Start a fault now (until :meth:`clear` or ``for_s`` seconds); returns it for :meth:`clear`."""
        fault = Fault(
            FaultKind(kind), tuple(channels), at_s=max(0.0, self.elapsed_s()), for_s=for_s, value=value
        )
        self._add(fault)
        return fault

    def clear(self, target: Fault | FaultKind | str | None = None) -> int:
        """End faults: one (``Fault``), all of a kind, or all (``None``). Returns how many were removed."""
        before = len(self._entries)
        if isinstance(target, Fault):
            self._entries = [e for e in self._entries if e.fault is not target]
        elif target is None:
            self._entries = []
        else:
            self._entries = [e for e in self._entries if e.fault.kind != FaultKind(target)]
        return before - len(self._entries)

    def _active_entries(self, kind: FaultKind | None = None) -> list[_Entry]:
        t = self.elapsed_s()
        return [e for e in self._entries if (kind is None or e.fault.kind == kind) and e.fault.active_at(t)]

    def active(self, kind: FaultKind | str | None = None) -> tuple[Fault, ...]:
        """Faults on now (of ``kind``, or all)."""
        return tuple(e.fault for e in self._active_entries(None if kind is None else FaultKind(kind)))

    def is_active(self, kind: FaultKind | str) -> bool:
        """Whether any fault of ``kind`` is on now."""
        return bool(self._active_entries(FaultKind(kind)))

    def first(self, kind: FaultKind | str) -> Fault | None:
        """The earliest-added active fault of ``kind``, if any."""
        entries = self._active_entries(FaultKind(kind))
        return entries[0].fault if entries else None

    def take_once(self, kind: FaultKind | str) -> Fault | None:
        """An active fault of ``kind`` not taken before (one-shot effects such as a counter gap)."""
        for e in self._active_entries(FaultKind(kind)):
            if not e.consumed:
                e.consumed = True
                return e.fault
        return None

    def signature(self) -> tuple[int, ...]:
        """Identifiers of the active faults: changes whenever the active set changes (cache key)."""
        return tuple(e.ident for e in self._active_entries())

    def channel_memory(self, fault: Fault) -> dict[int, float]:
        """Per-fault scratch space (channel → frozen value) used by :func:`apply_channel_faults`."""
        for e in self._entries:
            if e.fault is fault:
                return e.memory
        return {}


def apply_channel_faults(
    temps_c: NDArray[np.float64], status: NDArray[np.int64], faults: FaultController
) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """Copies of ``temps_c`` (°C) and ``status`` with the active channel faults applied.

    Channels out of the array's range are ignored (a fault for channel 40 on a 32-channel DAQ does nothing).
    """
    temps = np.array(temps_c, dtype=float, copy=True)
    stat = np.array(status, dtype=np.int64, copy=True)
    for fault in faults.active():
        if fault.kind not in CHANNEL_FAULTS:
            continue
        idx = [c - 1 for c in fault.channels if c <= temps.size]
        _apply_one(fault, idx, temps, stat, faults.channel_memory(fault))
    return temps, stat


def _apply_one(
    fault: Fault,
    idx: list[int],
    temps: NDArray[np.float64],
    stat: NDArray[np.int64],
    memory: dict[int, float],
) -> None:
    if fault.kind == FaultKind.OPEN_CIRCUIT:
        stat[idx] = 1
        if fault.value is not None:
            temps[idx] = fault.value
    elif fault.kind == FaultKind.OUT_OF_RANGE:
        stat[idx] = 2
        temps[idx] = fault.param()
    elif fault.kind == FaultKind.NAN:
        temps[idx] = math.nan
    elif fault.kind == FaultKind.STUCK:
        for i in idx:
            temps[i] = fault.value if fault.value is not None else memory.setdefault(i, float(temps[i]))
