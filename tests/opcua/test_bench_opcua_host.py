"""``python -m benchmarks opcua --spindles N``'s parts (issue 43, "Bars"): the pure figures (percentile,
medians and the REST ratio, the clients' spread over the spindles, the comparison of one spindle's OPC UA
values with its REST answer), ``benchmarks fleet --outlets`` (its settings and the host's refusal of what it
does not host yet), and one short real run of two hosted spindles (devices process, ``chtc run`` with
``[[spindles]]`` and ``[opcua]``, PostgreSQL, the readers' process, a CPU hog) whose figures come out
measured and whose spindles agree with REST. The run is slow: about two minutes."""

from __future__ import annotations

import argparse
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from benchmarks.fleet_host import Outlets, host_toml, parse_outlets, refused_by_host
from benchmarks.opcua_figures import UaValue, differences, median_or_none, percentile, rest_ratio, spread
from service.serve.opcua.status import UaStatus

AT = datetime(2026, 11, 29, 12, 0, 1, tzinfo=UTC)


@pytest.mark.parametrize("q", [0, 1, 50, 90, 99, 100])
def test_the_percentile_is_numpys_linear_one(q: float) -> None:
    xs = list(np.random.default_rng(3).exponential(2.0, size=137))
    assert percentile(xs, q) == pytest.approx(float(np.percentile(xs, q)))
    assert percentile([], q) is None
    assert percentile([4.0], q) == 4.0


def test_the_rest_ratio_is_of_the_medians_of_the_repeats() -> None:
    assert median_or_none([None, 3.0, 1.0, 2.0]) == 2.0
    assert median_or_none([None]) is None
    assert rest_ratio([3.0, 30.0, 4.0], [2.0, 1.0, 2.0]) == pytest.approx(2.0)  # 4 / 2: one outlier is not it
    assert rest_ratio([3.0], [None]) is None
    assert rest_ratio([3.0], [0.0]) is None


def test_the_reads_cover_every_spindle_evenly() -> None:
    counts = [0] * 10
    for k in range(10):
        for i in range(100):
            counts[spread(i, k, 10)] += 1
    assert counts == [100] * 10
    assert {spread(0, k, 10) for k in range(10)} == set(range(10))  # one instant: the clients on 10 spindles
    assert {spread(i, 3, 1) for i in range(5)} == {0}


def _rest(**kw: Any) -> dict[str, Any]:
    body = {
        "status": "fresh",
        "usable_for_compensation": True,
        "reason_code": None,
        "at": "2026-11-29T12:00:01Z",
        "axial": {"um": 12.3456},
        "plc": {"isg_temp_comp_offset_0_0p1um": 123},
    }
    return {**body, **kw}


def _ua(code: UaStatus = UaStatus.GOOD, **kw: Any) -> dict[str, UaValue]:
    values: dict[str, Any] = {
        "Status.Text": "fresh",
        "Status.Usable": True,
        "Status.Reason": "",
        "Status.Code": int(code),
        "Growth.Axial": 12.3456,
        "Growth.AxialCiLow95": 10.0,
        "Controller.SD43900Mm": 0.0123,
        "Controller.IsgOffset0p1um": 123,
        **kw,
    }
    status = {"Status.Text": 0, "Status.Usable": 0, "Status.Reason": 0, "Status.Code": 0}
    return {p: UaValue(v, status.get(p, int(code)), AT) for p, v in values.items()}


def test_a_spindle_equal_to_rest_has_no_differences() -> None:
    assert differences(_rest(), _ua()) == []
    held = _rest(status="converging", usable_for_compensation=False, reason_code="state_converging")
    ua = _ua(UaStatus.UNCERTAIN_LAST_USABLE_VALUE, **{"Status.Text": "converging", "Status.Usable": False})
    ua["Status.Reason"] = UaValue("state_converging", 0, AT)
    assert differences(held, ua) == []


def test_each_difference_from_rest_is_named() -> None:
    assert differences(_rest(), _ua(**{"Growth.Axial": 12.5})) == ["Growth.Axial: OPC UA 12.5, REST 12.3456"]
    later = _ua()
    later["Controller.SD43900Mm"] = UaValue(0.0123, 0, datetime(2026, 11, 29, 12, 0, 2, tzinfo=UTC))
    assert [d.split(":")[0] for d in differences(_rest(), later)] == ["Controller.SD43900Mm"]
    wrong_code = differences(_rest(), _ua(UaStatus.UNCERTAIN_SUB_NORMAL))
    assert any(d.startswith("Status.Code") and "GOOD" in d for d in wrong_code), wrong_code
    assert differences(_rest(usable_for_compensation=False), _ua())[0].startswith("Status.Usable")


def test_fleet_outlets_option_and_its_settings(tmp_path: Path) -> None:
    assert parse_outlets("opcua, MQTT") == {"opcua", "mqtt"}
    assert parse_outlets("") == parse_outlets("none") == frozenset()
    with pytest.raises(ValueError, match="unknown http"):
        parse_outlets("opcua,http")
    o = Outlets(opcua_port=4841, mqtt_port=1884, state_dir=str(tmp_path))
    assert o.flags() == {"opcua": True, "mqtt": True} and Outlets().flags() == {"opcua": False, "mqtt": False}
    text = host_toml(
        "sqlite://", 8000, [5020, 5021], [8001, 8002], Outlets(opcua_port=4841, max_connections=12)
    )
    assert "[opcua]\nenabled = true\nport = 4841\nmax_connections = 12\n" in text and "[mqtt]" not in text
    config = tmp_path / "host.toml"
    config.write_text(text, encoding="utf-8")
    assert refused_by_host(config) is None  # OPC UA is hosted
    config.write_text(host_toml("sqlite://", 8000, [5020, 5021], [8001, 8002], o), encoding="utf-8")
    refusal = refused_by_host(config)
    if refusal is not None:  # until MQTT is hosted: refused with a message naming the setting
        assert "[mqtt] enabled" in refusal


@pytest.mark.slow
@pytest.mark.postgres
@pytest.mark.timeout(600)
def test_a_short_hosted_opcua_run_measures_and_agrees_with_rest(pg_url: str) -> None:
    from benchmarks.opcua_host import run_host_bench

    args = argparse.Namespace(
        pg_url=pg_url,
        plants=2,
        runs=1,
        duration=3.0,
        settle=0.0,
        clients=4,
        read_rate=5.0,
        rate=20.0,
        rest_clients=2,
    )
    r = run_host_bench(2, args)
    assert r["spindles"] == 2 and r["clients"] == 4
    assert r["equal_to_rest"] is True, r["equal_to_rest_detail"]
    assert r["samples"]["reads_quiet"] == r["samples"]["reads_hog"] == 4 * 15
    assert r["samples"]["reads_per_spindle"] == {"bench-001": 30, "bench-002": 30}
    assert r["samples"]["rest_off"] == r["samples"]["rest_on"] == 60
    assert r["read_errors"] == 0 and r["rest_errors"] == 0
    for key in ("read_p50_ms", "read_p99_ms", "read_p99_ms_hog", "rest_p99_ms_outlets_off"):
        assert r[key] is not None and r[key] > 0, key
    assert r["read_p50_ms"] <= r["read_p99_ms"]
    assert r["rest_p99_ratio_outlets_on"] == pytest.approx(
        r["rest_p99_ms_outlets_on"] / r["rest_p99_ms_outlets_off"]
    )
    assert r["hog_processes"] >= 1 and datetime.fromisoformat(r["utc"]).tzinfo is not None
    assert [v["met"] for v in r["verdicts"]][-1] is True  # equal_to_rest
