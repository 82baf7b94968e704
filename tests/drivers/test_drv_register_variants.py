"""Register map variants real DAQs use, end to end over loopback: the simulated DAQ serves a map (input or
holding table; int16 … float64; word orders ABCD, CDAB, BADC, DCBA; scale and offset; a "no value" sentinel)
and the Modbus driver reads the same temperatures back. The word layout of each order is checked against
``struct`` independently of pymodbus."""

from __future__ import annotations

import asyncio
import math
import struct
from typing import Any

import numpy as np
import pytest

from drivers.errors import ConfigError, ModbusExceptionError
from drivers.modbus_daq import ModbusDaq
from drivers.registers import (
    WIDTHS,
    RegisterEntry,
    RegisterMap,
    decode_value,
    encode_value,
    register_map_from_dict,
)
from drivers.sim.faults import FaultController, FaultKind
from drivers.sim.modbus_server import SimulatedDaq
from drivers.sim.source import ArrayTimeline, TimelineSource

TEMPS = 20.0 + 0.37 * np.arange(32)


def _struct_words(fmt: str, value: float, order: str) -> list[int]:
    """Words in address order for ``order``, computed with ``struct`` (big-endian bytes A B C D ...)."""
    data = struct.pack(">" + fmt, value)
    words = [data[i : i + 2] for i in range(0, len(data), 2)]
    if order in ("CDAB", "DCBA"):
        words.reverse()
    if order in ("BADC", "DCBA"):
        words = [w[::-1] for w in words]
    return [int.from_bytes(w, "big") for w in words]


@pytest.mark.parametrize("order", ["ABCD", "CDAB", "BADC", "DCBA"])
@pytest.mark.parametrize(
    ("typ", "fmt", "value"),
    [
        ("int32", "i", -123456789),
        ("uint32", "I", 0x01020304),
        ("float32", "f", -12.375),
        ("float64", "d", 1e-3),
    ],
)
def test_word_orders_put_the_bytes_where_the_names_say(typ: str, fmt: str, value: float, order: str) -> None:
    e = RegisterEntry("x", 0, typ, 1.0, order, "housing", 1)  # type: ignore[arg-type]
    expected = _struct_words(fmt, value, order)
    assert encode_value(e, value) == expected
    assert decode_value(e, expected) == pytest.approx(value, rel=1e-12)


def test_known_layouts() -> None:
    e = {o: RegisterEntry("c", 0, "uint32", 1.0, o, "counter") for o in ("ABCD", "CDAB", "BADC", "DCBA")}
    assert encode_value(e["ABCD"], 0x01020304) == [0x0102, 0x0304]
    assert encode_value(e["CDAB"], 0x01020304) == [0x0304, 0x0102]
    assert encode_value(e["BADC"], 0x01020304) == [0x0201, 0x0403]
    assert encode_value(e["DCBA"], 0x01020304) == [0x0403, 0x0201]
    assert RegisterEntry("c", 0, "uint32", 1.0, "little", "counter").word_order == "CDAB"
    int16_swapped = RegisterEntry("t", 0, "int16", 0.01, "BADC", "housing", 1)
    assert encode_value(int16_swapped, 2.56) == [0x0001]  # raw 256 = 0x0100, bytes swapped


def test_offset_scale_and_sentinel() -> None:
    e = RegisterEntry("t", 0, "uint16", 0.1, "ABCD", "housing", 1, offset=-100.0, nodata=65535)
    assert encode_value(e, 25.0) == [1250]
    assert decode_value(e, [1250]) == pytest.approx(25.0)
    assert encode_value(e, math.nan) == [65535]
    assert math.isnan(decode_value(e, [65535]))
    f = RegisterEntry("t", 0, "float32", 1.0, "ABCD", "housing", 1, nodata=-9999.0)
    assert math.isnan(decode_value(f, encode_value(f, -9999.0)))
    assert math.isnan(decode_value(f, _struct_words("f", math.nan, "ABCD")))


@pytest.mark.parametrize(
    ("raw", "entry"),
    [
        ({"type": "int32", "nodata": 2**31}, "T01"),
        ({"type": "float64", "role": "counter"}, "c"),
        ({"type": "int16", "word_order": "ABDC"}, "T01"),
        ({"type": "int16", "offset": math.inf}, "T01"),
    ],
)
def test_bad_variants_name_the_entry(raw: dict[str, Any], entry: str) -> None:
    d = {"name": entry, "address": 0, "role": "housing", "channel": 1} | raw
    if raw.get("role") == "counter":
        d.pop("channel")
    with pytest.raises(ConfigError, match=entry):
        RegisterMap((register_map_from_dict({"n_channels": 1, "register": [d]}).entries[0],), n_channels=1)


def test_unknown_table_and_keys_are_refused() -> None:
    with pytest.raises(ConfigError, match="table 'coils'"):
        register_map_from_dict(_variant("coils", "int16", "ABCD"))
    bad = _variant("input", "int16", "ABCD")
    bad["group"][0]["colour"] = "red"
    with pytest.raises(ConfigError, match=r"T: unknown keys \['colour'\]"):
        register_map_from_dict(bad)


def _variant(
    table: str, typ: str, order: str, *, scale: float = 1.0, offset: float = 0.0, nodata: float | None = None
) -> dict[str, Any]:
    """A 32-channel map in TOML form: temperatures and ambient of ``typ``, status uint16 and counter uint32,
    all in word order ``order``."""
    value: dict[str, Any] = {"type": typ, "word_order": order, "scale": scale, "offset": offset}
    if nodata is not None:
        value["nodata"] = nodata
    width = WIDTHS.get(typ, 1)
    return {
        "table": table,
        "n_channels": 32,
        "group": [
            {"prefix": "T", "address": 0, "count": 32, "first_channel": 1, "role": "housing", **value},
            {
                "prefix": "S",
                "address": 300,
                "count": 32,
                "first_channel": 1,
                "type": "uint16",
                "role": "status",
            }
            | {"word_order": order},
        ],
        "register": [
            {"name": "amb", "address": 32 * width, "role": "ambient", **value},
            {"name": "cnt", "address": 400, "type": "uint32", "word_order": order, "role": "counter"},
        ],
    }


VARIANTS = [
    ("input", "int16", "ABCD", 0.01, 0.0, None, 0.005),
    ("holding", "int16", "BADC", 0.01, 0.0, None, 0.005),
    ("holding", "uint16", "DCBA", 0.1, -100.0, 65535, 0.05),
    ("input", "int32", "CDAB", 0.001, 0.0, -(2**31), 0.0005),
    ("holding", "int32", "DCBA", 0.0001, 273.15, -(2**31), 0.00005),
    ("holding", "uint32", "BADC", 0.001, -50.0, 0xFFFFFFFF, 0.0005),
    ("input", "float32", "CDAB", 1.0, 0.0, None, 1e-5),
    ("holding", "float32", "BADC", 1.0, 0.0, None, 1e-5),
    ("holding", "float32", "DCBA", 1.0, 0.0, None, 1e-5),
    ("input", "float64", "ABCD", 1.0, 0.0, None, 1e-12),
    ("holding", "float64", "DCBA", 1.0, -273.15, None, 1e-9),
]


@pytest.mark.parametrize(("table", "typ", "order", "scale", "offset", "nodata", "tol"), VARIANTS)
def test_each_variant_end_to_end_over_loopback(
    table: str, typ: str, order: str, scale: float, offset: float, nodata: float | None, tol: float
) -> None:
    reg_map = register_map_from_dict(_variant(table, typ, order, scale=scale, offset=offset, nodata=nodata))
    faults = FaultController()

    async def main() -> None:
        source = TimelineSource(ArrayTimeline.constant(temps_c=TEMPS, ambient_c=21.5))
        async with SimulatedDaq(source, port=0, register_map=reg_map, faults=faults, counter_start=7) as sim:
            async with ModbusDaq("127.0.0.1", sim.port, register_map=reg_map, timeout_s=1.0) as daq:
                r = await daq.read()
                np.testing.assert_allclose(r.temps_c, TEMPS, atol=tol * 1.001, rtol=0)
                assert r.ambient_c == pytest.approx(21.5, abs=tol * 1.001)
                assert r.counter == 7 and set(r.status.tolist()) == {0}
                faults.inject(FaultKind.NAN, channels=(5,))
                faults.inject(FaultKind.OPEN_CIRCUIT, channels=(9,))
                r = await daq.read()
                assert math.isnan(r.temps_c[4]) and r.status[8] == 1
                np.testing.assert_allclose(
                    np.delete(r.temps_c, 4), np.delete(TEMPS, 4), atol=tol * 1.001, rtol=0
                )
            # a driver reading the other table is refused by the device
            other = RegisterMap(
                reg_map.entries, n_channels=32, table="input" if table == "holding" else "holding"
            )
            async with ModbusDaq("127.0.0.1", sim.port, register_map=other, timeout_s=1.0) as daq:
                with pytest.raises(
                    ModbusExceptionError, match=r"exception 1 \(illegal function\) for FC[34]"
                ):
                    await daq.read()

    asyncio.run(main())
