"""Register map: validation names the entry, encode/decode round trips, word orders, blocks, TOML."""

from __future__ import annotations

import math
import struct
from pathlib import Path

import numpy as np
import pytest

from drivers.errors import ConfigError, EncodeError, ShortReplyError
from drivers.registers import (
    RegisterEntry,
    RegisterMap,
    RegisterValues,
    decode,
    decode_value,
    default_register_map,
    encode,
    encode_value,
    load_register_map,
    read_blocks,
    register_map_from_dict,
)

PACKAGED_TOML = Path(__file__).resolve().parents[2] / "drivers" / "data" / "registers.toml"


def _temps(n: int = 32, *, start: int = 0, step: int = 1, typ: str = "int16") -> list[RegisterEntry]:
    role = "bearing"
    return [
        RegisterEntry(f"T{c}", start + step * (c - 1), typ, 0.01, "big", role, c)  # type: ignore[arg-type]
        for c in range(1, n + 1)
    ]


def _ambient(addr: int = 64) -> RegisterEntry:
    return RegisterEntry("amb", addr, "int16", 0.01, "big", "ambient", None)


def test_default_map_matches_spec_section_4() -> None:
    m = default_register_map()
    temps = m.temperatures()
    assert [e.address for e in temps] == list(range(32))
    assert all(e.type == "int16" and e.scale == 0.01 for e in temps)
    assert m.role("ambient")[0].address == 32
    assert [e.address for e in m.role("status")] == list(range(100, 133))
    (counter,) = m.role("counter")
    assert (counter.address, counter.type, counter.word_order) == (200, "uint32", "ABCD")
    assert m.bearing_channels() == tuple(range(1, 13))
    assert read_blocks(m) == [(0, 33), (100, 33), (200, 2)]


def test_packaged_toml_equals_default_map() -> None:
    loaded = load_register_map(PACKAGED_TOML)
    default = default_register_map()
    by_addr = {e.address: e for e in default.entries}
    assert len(loaded.entries) == len(default.entries)
    for e in loaded.entries:
        d = by_addr[e.address]
        assert (e.type, e.scale, e.word_order, e.role, e.channel) == (
            d.type,
            d.scale,
            d.word_order,
            d.role,
            d.channel,
        )


@pytest.mark.parametrize(
    ("entries", "named"),
    [
        ([*_temps()[:-1], RegisterEntry("T32", 30, "int16", 0.01, "big", "housing", 32), _ambient()], "T32"),
        ([*_temps()[:-1], RegisterEntry("dup", 40, "int16", 0.01, "big", "housing", 5), _ambient()], "dup"),
        ([*_temps()[:-1], _ambient()], "channels"),
        ([*_temps(), _ambient(), RegisterEntry("c", 70, "float32", 1.0, "big", "counter", None)], "'c'"),
        ([*_temps(), _ambient(), RegisterEntry("w", 70, "int64", 1.0, "big", "status", 1)], "'w'"),  # type: ignore[arg-type]
        ([*_temps(), _ambient(), RegisterEntry("s99", 70, "uint16", 1.0, "big", "status", 99)], "s99"),
        ([*_temps(), _ambient(), RegisterEntry("z", 70, "int16", 0.0, "big", "status", 1)], "z"),
        (_temps(), "ambient"),
        ([*_temps(), _ambient(), RegisterEntry("T1", 90, "int16", 1.0, "big", "status", 2)], "T1"),
    ],
    ids=[
        "overlap",
        "duplicate-channel",
        "missing-channel",
        "float-counter",
        "bad-type",
        "bad-channel",
        "zero-scale",
        "no-ambient",
        "duplicate-name",
    ],
)
def test_validation_errors_name_the_entry(entries: list[RegisterEntry], named: str) -> None:
    with pytest.raises(ConfigError) as info:
        RegisterMap(tuple(entries))
    assert named.strip("'") in str(info.value)


def test_overlap_of_32_bit_entry_names_both() -> None:
    entries = [
        *_temps(),
        _ambient(),
        RegisterEntry("cnt", 70, "uint32", 1.0, "big", "counter", None),
        RegisterEntry("S1", 71, "uint16", 1.0, "big", "status", 1),
    ]
    with pytest.raises(ConfigError, match=r"S1.*overlaps 'cnt'"):
        RegisterMap(tuple(entries))


@pytest.mark.parametrize("order", ["big", "little"])
def test_float32_word_orders(order: str) -> None:
    e = RegisterEntry("f", 10, "float32", 1.0, order, "bearing", 1)  # type: ignore[arg-type]
    hi, lo = struct.unpack(">HH", struct.pack(">f", -12.375))
    words = encode_value(e, -12.375)
    assert words == ([hi, lo] if order == "big" else [lo, hi])
    assert decode_value(e, words) == -12.375
    assert math.isnan(decode_value(e, encode_value(e, math.nan)))


def test_int16_negative_and_nan_sentinel() -> None:
    e = RegisterEntry("t", 0, "int16", 0.01, "big", "bearing", 1)
    assert encode_value(e, -5.25) == [0x10000 - 525]
    assert decode_value(e, [0x10000 - 525]) == pytest.approx(-5.25)
    assert encode_value(e, math.nan) == [0x8000]
    assert math.isnan(decode_value(e, [0x8000]))
    with pytest.raises(EncodeError, match="t: value 400"):
        encode_value(e, 400.0)


def test_uint32_big_and_little_word_order() -> None:
    big = RegisterEntry("c", 0, "uint32", 1.0, "big", "counter", None)
    little = RegisterEntry("c", 0, "uint32", 1.0, "little", "counter", None)
    assert encode_value(big, 0x12345678) == [0x1234, 0x5678]
    assert encode_value(little, 0x12345678) == [0x5678, 0x1234]
    assert decode_value(little, [0x5678, 0x1234]) == 0x12345678


def test_encode_decode_round_trip_default_map() -> None:
    m = default_register_map()
    rng = np.random.default_rng(3)
    temps = np.round(rng.uniform(-30, 120, 32), 2)
    temps[7] = np.nan
    status = rng.integers(0, 3, 32)
    values = RegisterValues(temps, 21.37, status, 1, 4_000_000_000)
    words = encode(m, values)
    assert set(words) == {a for s, c in read_blocks(m) for a in range(s, s + c)}
    back = decode(m, words)
    np.testing.assert_allclose(back.temps_c, temps, atol=1e-9)
    assert (back.ambient_c, back.ambient_status, back.counter) == (pytest.approx(21.37), 1, 4_000_000_000)
    np.testing.assert_array_equal(back.status, status)
    blocks = [(s, [words[a] for a in range(s, s + c)]) for s, c in read_blocks(m)]
    np.testing.assert_allclose(decode(m, blocks).temps_c, temps)


def test_decode_missing_word_names_the_entry() -> None:
    m = default_register_map()
    words = encode(m, RegisterValues(np.zeros(32), 20.0, np.zeros(32, dtype=np.int64), 0, 1))
    del words[201]
    with pytest.raises(ShortReplyError, match=r"200-201.*got 1.*counter"):
        decode(m, words)


def test_read_blocks_merges_adjacent_and_caps_at_125() -> None:
    # 64 float32 channels (registers 0..127) + ambient at 128: one contiguous run of 129 registers.
    m = RegisterMap((*_temps(64, start=0, step=2, typ="float32"), _ambient(128)), n_channels=64)
    blocks = read_blocks(m)
    # 125 is odd, so the first request stops at 124 registers rather than split a float32.
    assert blocks == [(0, 124), (124, 5)]
    starts = {s for s, _ in blocks}
    assert all(not (e.address < s <= e.last_address) for e in m.entries for s in starts)


def test_read_blocks_does_not_bridge_gaps() -> None:
    m = RegisterMap((*_temps(32), _ambient(40)))
    assert read_blocks(m) == [(0, 32), (40, 1)]


def test_toml_errors_name_entry(tmp_path: Path) -> None:
    p = tmp_path / "map.toml"
    p.write_text('[[register]]\nname = "amb"\naddress = "x"\nrole = "ambient"\n')
    with pytest.raises(ConfigError, match="amb"):
        load_register_map(p)
    p.write_text("this is = = not toml")
    with pytest.raises(ConfigError, match=r"map\.toml"):
        load_register_map(p)
    with pytest.raises(ConfigError, match="bogus"):
        register_map_from_dict({"register": [{"name": "bogus", "address": 1, "colour": "red"}]})


def test_float32_little_endian_map_from_dict() -> None:
    raw = {
        "n_channels": 2,
        "group": [
            {
                "prefix": "T",
                "address": 0,
                "count": 2,
                "first_channel": 1,
                "type": "float32",
                "word_order": "little",
                "scale": 1.0,
                "role": "housing",
            }
        ],
        "register": [
            {"name": "amb", "address": 4, "type": "float32", "word_order": "little", "role": "ambient"}
        ],
    }
    m = register_map_from_dict(raw)
    assert [e.address for e in m.entries] == [0, 2, 4]
    words = encode(m, {"T01": 1.5, "T02": -40.25, "amb": 22.0})
    out = decode(m, words)
    np.testing.assert_array_equal(out.temps_c, [1.5, -40.25])
    assert out.counter is None


def test_vectorised_decode_matches_scalar_decode_for_every_type_and_order() -> None:
    """``decode`` (numpy, all entries at once) equals ``decode_value`` (pymodbus' conversion, per entry)."""
    rng = np.random.default_rng(7)
    types = ["int16", "uint16", "int32", "uint32", "float32", "float64"]
    orders = ["ABCD", "CDAB", "BADC", "DCBA"]
    entries, addr = [], 0
    for c in range(1, 33):
        typ, order = types[c % 6], orders[(c // 6) % 4]
        nodata = {"int16": None, "uint16": 65535.0, "int32": -(2.0**31)}.get(typ)
        e = RegisterEntry(
            f"T{c}",
            addr,
            typ,
            float(rng.choice([0.01, 0.1, 1.0])),
            order,
            "housing",
            c,  # type: ignore[arg-type]
            offset=float(rng.choice([0.0, -273.15])),
            nodata=nodata,
        )
        entries.append(e)
        addr += e.width + int(rng.integers(0, 2))
    entries += [
        RegisterEntry("amb", addr, "float32", 1.0, "BADC", "ambient", None),
        RegisterEntry("cnt", addr + 2, "uint32", 1.0, "DCBA", "counter", None),
        RegisterEntry("S0", addr + 4, "uint16", 1.0, "BADC", "status", 0),
    ]
    m = RegisterMap(tuple(entries))
    sentinel_entries = [e for e in m.entries if e.no_value is not None]
    for _ in range(20):
        words = {
            a: int(rng.integers(0, 0x10000)) for e in m.entries for a in range(e.address, e.last_address + 1)
        }
        for e in sentinel_entries[:3]:  # the "no value" sentinels
            words.update(zip(range(e.address, e.last_address + 1), encode_value(e, math.nan), strict=True))
        out = decode(m, words)
        for e in m.entries:
            expected = decode_value(e, [words[a] for a in range(e.address, e.last_address + 1)])
            got = _decoded(out, e)
            assert (math.isnan(got) and math.isnan(expected)) or got == pytest.approx(expected, rel=1e-12), (
                e.name
            )
        assert sum(math.isnan(_decoded(out, e)) for e in sentinel_entries[:3]) == 3


def _decoded(out: RegisterValues, e: RegisterEntry) -> float:
    if e.role == "housing":
        return float(out.temps_c[(e.channel or 1) - 1])
    if e.role == "ambient":
        return out.ambient_c
    if e.role == "counter":
        return float(out.counter or 0)
    return float(out.ambient_status)
