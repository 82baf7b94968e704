"""DBC layout and can_codec: byte layout derived independently with struct, typed errors."""

from __future__ import annotations

import struct
from pathlib import Path

import pytest

from drivers.can_codec import SensorStatus, counter_gap, decode_frame, encode_status, load_dbc
from drivers.errors import BadSignalError, ConfigError, EncodeError, UnknownFrameIdError, WrongDlcError


def test_dbc_message_matches_spec() -> None:
    msg = load_dbc().get_message_by_name("SpindleStatus")
    assert (msg.frame_id, msg.length, msg.is_extended_frame) == (0x181, 6, False)


@pytest.mark.parametrize(
    ("speed", "torque", "counter", "status"),
    [(0, 0.0, 0, 0), (3000, 12.34, 5, 1), (65535, -327.68, 15, 2), (7000, -0.01, 9, 0)],
)
def test_layout_is_little_endian_as_documented(speed: int, torque: float, counter: int, status: int) -> None:
    expected = struct.pack("<HhBB", speed, round(torque * 100), counter, status)
    data = encode_status(speed, torque, counter, status)
    assert data == expected
    decoded = decode_frame(0x181, data)
    assert (decoded.speed_rpm, decoded.torque_nm, decoded.counter) == (speed, pytest.approx(torque), counter)
    assert decoded.status is SensorStatus(status)


def test_decode_errors_are_typed_and_name_the_frame() -> None:
    good = encode_status(1000, 1.0, 1, 0)
    with pytest.raises(UnknownFrameIdError, match="0x182"):
        decode_frame(0x182, good)
    with pytest.raises(UnknownFrameIdError, match="extended"):
        decode_frame(0x181, good, is_extended_id=True)
    with pytest.raises(WrongDlcError, match=r"0x181 \(DLC 5\).*expected 6") as info:
        decode_frame(0x181, good[:5])
    assert info.value.expected_dlc == 6
    with pytest.raises(BadSignalError, match="status byte 7"):
        decode_frame(0x181, good[:5] + b"\x07")


def test_encode_errors() -> None:
    with pytest.raises(EncodeError, match="Counter"):
        encode_status(1000, 0.0, 16, 0)
    with pytest.raises(EncodeError, match="SpindleStatus"):
        encode_status(70000, 0.0, 0, 0)


def test_counter_gap_modulo_16() -> None:
    assert counter_gap(3, 4) == 0
    assert counter_gap(15, 0) == 0
    assert counter_gap(14, 2) == 3
    assert counter_gap(5, 5) == 15


def test_bad_dbc_file_names_the_file(tmp_path: Path) -> None:
    p = tmp_path / "empty.dbc"
    p.write_text('VERSION ""\n\nNS_ :\n\nBS_:\n\nBU_:\n')
    with pytest.raises(ConfigError, match=r"empty\.dbc"):
        load_dbc(p)
    with pytest.raises(ConfigError, match=r"missing\.dbc"):
        load_dbc(tmp_path / "missing.dbc")


def test_a_decoded_payload_is_remembered_and_a_bad_one_raises_every_time() -> None:
    """``decode_frame`` caches decoded payloads (the sensor repeats a few at 100 frames/s); it must give the
    same answer as a first decode, keep a bytearray from aliasing its key, and never cache a failure."""
    buf = bytearray(encode_status(4321, 2.5, 3, 1))
    first = decode_frame(0x181, buf)
    buf[0] ^= 0xFF  # the caller reuses its buffer: the cached entry must not change with it
    assert decode_frame(0x181, encode_status(4321, 2.5, 3, 1)) == first
    assert decode_frame(0x181, buf).speed_rpm != first.speed_rpm
    bad = encode_status(4321, 2.5, 3, 0)[:5] + b"\x09"
    for _ in range(2):
        with pytest.raises(BadSignalError, match="status byte 9"):
            decode_frame(0x181, bad)
