"""Encode/decode the speed/torque sensor's CAN frames with cantools and the packaged DBC.

``drivers/data/spindle.dbc`` describes ``SpindleStatus`` (ID 0x181, CAN 2.0A, DLC 6, little-endian/Intel):

====  ======  ==========================================  ===========
byte  bits    signal                                      scale
====  ======  ==========================================  ===========
0-1   0-15    Speed, uint16                               1 rpm/bit
2-3   16-31   Torque, int16                               0.01 N·m/bit
4     32-35   Counter, 4-bit rolling (+1 per frame mod 16) (bits 36-39 reserved, 0)
5     40-47   Status, uint8: 0 ok, 1 warning, 2 fault
====  ======  ==========================================  ===========

cantools errors are translated here, once: unknown ID → ``UnknownFrameIdError``, wrong length →
``WrongDlcError``, undecodable payload or a status byte outside {0, 1, 2} → ``BadSignalError``, a value
that does not fit a signal → ``EncodeError``. Pure functions; the DBC is read lazily on first use,
never at import.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from enum import IntEnum
from importlib import resources
from pathlib import Path

import cantools
import cantools.database
from cantools.database.can import Database, Message

from drivers.errors import BadSignalError, ConfigError, EncodeError, UnknownFrameIdError, WrongDlcError

SPINDLE_STATUS_ID = 0x181
SPINDLE_STATUS_NAME = "SpindleStatus"
COUNTER_MODULO = 16


class SensorStatus(IntEnum):
    """The sensor's self-reported status byte."""

    OK = 0
    WARNING = 1
    FAULT = 2


@dataclass(frozen=True)
class SpindleStatus:
    """One decoded ``SpindleStatus`` frame: speed rpm, torque N·m, rolling counter 0..15, status."""

    speed_rpm: float
    torque_nm: float
    counter: int
    status: SensorStatus


def default_dbc_path() -> Path:
    """Path of the packaged ``drivers/data/spindle.dbc``."""
    return Path(str(resources.files("drivers") / "data" / "spindle.dbc"))


@functools.lru_cache(maxsize=8)
def load_dbc(path: str | Path | None = None) -> Database:
    """Load and check a DBC (``None``: the packaged one).

    Raises ``ConfigError`` naming the file or message."""
    p = Path(path) if path is not None else default_dbc_path()
    try:
        db = cantools.database.load_file(str(p), database_format="dbc")
    except (OSError, cantools.database.UnsupportedDatabaseFormatError, ValueError) as err:
        raise ConfigError(f"cannot load DBC: {err}", entry=str(p)) from err
    if not isinstance(db, Database):
        raise ConfigError("not a CAN database", entry=str(p))
    try:
        msg = db.get_message_by_name(SPINDLE_STATUS_NAME)
    except KeyError as err:
        raise ConfigError(f"message {SPINDLE_STATUS_NAME} missing", entry=str(p)) from err
    missing = {"Speed", "Torque", "Counter", "Status"} - {s.name for s in msg.signals}
    if missing:
        raise ConfigError(f"signals {sorted(missing)} missing", entry=f"{p}:{SPINDLE_STATUS_NAME}")
    return db


def _status_message(db: Database | None) -> Message:
    return (db or load_dbc()).get_message_by_name(SPINDLE_STATUS_NAME)


def encode_status(
    speed_rpm: float, torque_nm: float, counter: int, status: int, *, db: Database | None = None
) -> bytes:
    """Payload of a ``SpindleStatus`` frame (6 bytes). ``counter`` 0..15; ``status`` 0..255 (values other than
    0/1/2 are allowed so a simulator can send invalid ones). Raises ``EncodeError`` naming the signal."""
    if not 0 <= int(counter) < COUNTER_MODULO:
        raise EncodeError(f"{SPINDLE_STATUS_NAME}.Counter: {counter} outside 0..15")
    if not 0 <= int(status) <= 0xFF:
        raise EncodeError(f"{SPINDLE_STATUS_NAME}.Status: {status} outside 0..255")
    signals = {"Speed": speed_rpm, "Torque": torque_nm, "Counter": int(counter), "Status": int(status)}
    try:
        return bytes(_status_message(db).encode(signals, scaling=True, strict=True))
    except cantools.database.EncodeError as err:
        raise EncodeError(f"{SPINDLE_STATUS_NAME}: {err}") from err


def decode_frame(
    arbitration_id: int, data: bytes | bytearray, *, is_extended_id: bool = False, db: Database | None = None
) -> SpindleStatus:
    """Decode one frame. Raises ``UnknownFrameIdError`` (ID not ``SpindleStatus`` or extended),
    ``WrongDlcError`` (length differs from the DBC) or ``BadSignalError`` (status byte not 0/1/2).

    Decoded payloads are remembered (``DECODED_CACHE`` of them, least recently used dropped): the sensor
    repeats a few payloads (16 counter values per speed and torque) at 100 frames/s; cantools takes about
    8 µs for one, the cache 0.5 µs. Failures are not remembered: a bad frame raises every time."""
    return _decode_cached(int(arbitration_id), bytes(data), bool(is_extended_id), db or load_dbc())


DECODED_CACHE = 256


@functools.lru_cache(maxsize=DECODED_CACHE)
def _decode_cached(arbitration_id: int, data: bytes, is_extended_id: bool, db: Database) -> SpindleStatus:
    dlc = len(data)
    msg = _status_message(db)
    if is_extended_id != msg.is_extended_frame or arbitration_id != msg.frame_id:
        kind = "extended " if is_extended_id else ""
        raise UnknownFrameIdError(f"unknown {kind}ID", arbitration_id=arbitration_id, dlc=dlc)
    if dlc != msg.length:
        raise WrongDlcError(arbitration_id=arbitration_id, dlc=dlc, expected_dlc=msg.length)
    try:
        decoded = msg.decode(data, decode_choices=False, scaling=True)
        sig = {k: float(v) for k, v in dict(decoded).items()}  # type: ignore[arg-type]
    except (cantools.database.DecodeError, TypeError, ValueError) as err:
        raise BadSignalError(str(err), arbitration_id=arbitration_id, dlc=dlc) from err
    raw_status = int(sig["Status"])
    if raw_status not in SensorStatus._value2member_map_:
        raise BadSignalError(f"status byte {raw_status} not 0/1/2", arbitration_id=arbitration_id, dlc=dlc)
    return SpindleStatus(
        speed_rpm=sig["Speed"],
        torque_nm=round(sig["Torque"], 2),
        counter=int(sig["Counter"]),
        status=SensorStatus(raw_status),
    )


def frame_counter(data: bytes | bytearray, *, db: Database | None = None) -> int | None:
    """The rolling counter of a ``SpindleStatus`` payload that was rejected for another reason (bad status
    byte, too long), or ``None`` when the payload is too short to hold it. Reads the DBC's ``Counter``
    signal position (little-endian), without checking the other signals."""
    sig = _status_message(db).get_signal_by_name("Counter")
    if len(data) * 8 < sig.start + sig.length:
        return None
    return (int.from_bytes(bytes(data), "little") >> sig.start) & ((1 << sig.length) - 1)


def counter_gap(previous: int, current: int) -> int:
    """Frames missed between two rolling-counter values (0 = consecutive; 15 means a repeat or 15 lost)."""
    return (int(current) - int(previous) - 1) % COUNTER_MODULO
