"""Round trips of every model (aware UTC in and out), pagination, time filters, nearest-condition lookup."""

from __future__ import annotations

import math
from datetime import UTC, datetime, timedelta, timezone

import numpy as np
import pytest
from sqlalchemy.orm import Session, sessionmaker

from service.contracts.records import (
    ConditionEnd,
    ConditionStart,
    DeviceEventData,
    IdentificationData,
    SampleData,
)
from service.serve.views import row_to_record
from service.store import repository as repo
from service.store.errors import RecordError, RecordNotFoundError
from service.store.models import Condition, DeviceEvent, Identification, SampleRow

T0 = datetime(2026, 3, 1, 8, 0, 0, 123456, tzinfo=UTC)
CEST = timezone(timedelta(hours=2))


def ident(ident_id: int, condition_id: int, finished: datetime, **kw: object) -> IdentificationData:
    base: dict[str, object] = {
        "id": ident_id,
        "condition_id": condition_id,
        "started_at": finished - timedelta(seconds=2),
        "finished_at": finished,
        "window_start": finished - timedelta(minutes=60),
        "window_end": finished - timedelta(seconds=3),
        "reason": "schedule",
        "outcome": "ok",
        "method": "hybrid",
        "model_version": "geo-abc/mesh-4mm/rom30",
        "h": [80.0 + ident_id, 46.0, 68.0, 46.0, 52.0, 70.0, 16.0],
        "duration_s": 0.6,
    }
    base.update(kw)
    return IdentificationData(**base)  # type: ignore[arg-type]


def add_condition(
    factory: sessionmaker[Session], cid: int, point: tuple[float, float, float], t: datetime
) -> None:
    with repo.session_scope(factory) as s:
        speed, torque, ambient = point
        repo.add_condition(
            s, ConditionStart(id=cid, started_at=t, speed_rpm=speed, torque_nm=torque, ambient_c=ambient)
        )


def test_condition_round_trip_converts_offsets_to_utc(factory: sessionmaker[Session]) -> None:
    started = datetime(2026, 3, 1, 10, 0, 0, 5, tzinfo=CEST)  # 08:00:00.000005 UTC
    with repo.session_scope(factory) as s:
        repo.add_condition(
            s, ConditionStart(id=7, started_at=started, speed_rpm=4000.0, torque_nm=10.5, ambient_c=21.8)
        )
    with repo.session_scope(factory) as s:
        repo.end_condition(s, ConditionEnd(7, started + timedelta(minutes=90)))
    with repo.session_scope(factory) as s:
        row = repo.get_condition(s, 7)
    assert row.started_at == started and row.started_at.tzinfo is UTC
    assert row.started_at.hour == 8 and row.started_at.microsecond == 5
    assert row.ended_at == started + timedelta(minutes=90) and row.ended_at.tzinfo is UTC
    assert (row.speed_rpm, row.torque_nm, row.ambient_c) == (4000.0, 10.5, 21.8)


def test_identification_round_trip_every_field(factory: sessionmaker[Session]) -> None:
    add_condition(factory, 1, (3000.0, 8.0, 23.2), T0)
    data = ident(
        5,
        1,
        T0 + timedelta(hours=1),
        ci95_lo=[70.0, 40.0, 60.0, 30.0, 50.0, 60.0, math.nan],
        ci95_hi=[90.0, 50.0, 75.0, 60.0, 54.0, 80.0, math.inf],
        identified=[True, True, True, False, True, True, False],
        load_scale=(1.02, 0.97),
        f=0.04,
        fit=1 / 1.04,
        rmse_c=0.2,
        nfev=4200,
        n_sensors_used=31,
        warm_start_source="condition 0",
        warm_start_id=3,
        message="converged",
        diagnostics={"test_points": {1: {"me": 0.5}}, "rmse_per_sensor": [0.1, math.nan]},
    )
    with repo.session_scope(factory) as s:
        repo.add_identification(s, data)
    with repo.session_scope(factory) as s:
        row = repo.get_identification(s, 5)
    assert row.h == tuple(data.h or ())
    assert row.ci95_lo == [70.0, 40.0, 60.0, 30.0, 50.0, 60.0, None]  # NaN/inf stored as NULL
    assert row.ci95_hi is not None and row.ci95_hi[-1] is None
    assert row.identified == list(data.identified or ())
    assert (row.load_scale_front, row.load_scale_rear) == (1.02, 0.97)
    assert (row.f, row.fit, row.rmse_c, row.nfev, row.n_sensors_used) == (0.04, 1 / 1.04, 0.2, 4200, 31)
    assert (row.warm_start_source, row.warm_start_id, row.message) == ("condition 0", 3, "converged")
    assert row.diagnostics == {"test_points": {"1": {"me": 0.5}}, "rmse_per_sensor": [0.1, None]}
    for name in ("started_at", "finished_at", "window_start", "window_end"):
        assert getattr(row, name) == getattr(data, name) and getattr(row, name).tzinfo is UTC, name
    assert IdentificationData.from_row(row).values() == data.values()  # the stored record reads back whole
    record = row_to_record(row)
    assert record.condition.id == 1 and record.condition.speed_rpm == 3000.0
    np.testing.assert_array_equal(record.h, data.h)
    assert np.isnan(record.ci95_lo[6]) and record.identified.dtype == bool
    assert record.wall_s == 0.6 and record.window_from == data.window_start


def test_failed_identification_without_h(factory: sessionmaker[Session]) -> None:
    add_condition(factory, 1, (3000.0, 8.0, 23.2), T0)
    data = ident(2, 1, T0, outcome="insufficient-data", h=None, message="only 12 good channels")
    with repo.session_scope(factory) as s:
        repo.add_identification(s, data)
    with repo.session_scope(factory) as s:
        row = repo.get_identification(s, 2)
        assert row.h == (None,) * 7 and row.outcome == "insufficient-data"
        assert repo.last_identification(s) is None  # only successful ones by default
        assert repo.last_identification(s, outcome=None) is not None
    assert np.isnan(row_to_record(row).h).all()


def test_device_event_and_sample_round_trip(factory: sessionmaker[Session]) -> None:
    temps = [20.0 + 0.25 * i for i in range(32)]
    temps[6] = math.nan
    quality = ["ok"] * 32
    quality[6] = "open_circuit"
    sample = SampleData(
        t=T0,
        temps_c=temps,
        ambient_c=22.5,
        speed_rpm=4000.0,
        torque_nm=-1.25,
        quality=quality,
        can_ok=True,
        daq_ok=False,
    )
    with repo.session_scope(factory) as s:
        repo.add_device_event(
            s,
            DeviceEventData(
                t=T0.astimezone(CEST), device="modbus", kind="timeout", detail="unit 1 after 1.0 s"
            ),
        )
        repo.add_samples(s, [sample])
    with repo.session_scope(factory) as s:
        (event,) = repo.list_device_events(s).items
        (row,) = repo.list_samples(s)
    assert (event.t, event.t.tzinfo, event.device, event.kind) == (T0, UTC, "modbus", "timeout")
    assert event.detail == "unit 1 after 1.0 s"
    assert row.t == T0 and row.t.tzinfo is UTC
    assert row.temps_c[:6] == temps[:6] and row.temps_c[6] is None and row.temps_c[7:] == temps[7:]
    assert (row.ambient_c, row.speed_rpm, row.torque_nm) == (22.5, 4000.0, -1.25)
    assert (row.n_good, row.bad_channels, row.can_ok, row.daq_ok) == (31, {"7": "open_circuit"}, True, False)


def test_naive_datetimes_are_refused(factory: sessionmaker[Session]) -> None:
    with pytest.raises(RecordError, match=r"ConditionStart\.started_at: naive"):
        ConditionStart(id=1, started_at=datetime(2026, 1, 1), speed_rpm=1.0, torque_nm=1.0, ambient_c=1.0)
    with pytest.raises(RecordError, match="naive datetime"), repo.session_scope(factory) as s:
        s.add(DeviceEvent(t=datetime(2026, 1, 1), device="can", kind="x", detail=""))
        s.flush()


def test_bad_records_are_typed_errors(factory: sessionmaker[Session]) -> None:
    with pytest.raises(RecordError, match="outcome"):
        ident(1, 1, T0, outcome="great")
    with pytest.raises(RecordError, match=r"IdentificationData\.h: expected 7"):
        ident(1, 1, T0, h=[1.0, 2.0])
    with pytest.raises(RecordError, match="rejected"), repo.session_scope(factory) as s:
        repo.add_identification(s, ident(1, 99, T0))  # no condition 99: the foreign key holds (SQLite too)
    add_condition(factory, 1, (1.0, 1.0, 1.0), T0)
    with pytest.raises(RecordError, match="rejected"), repo.session_scope(factory) as s:
        repo.add_condition(
            s, ConditionStart(id=1, started_at=T0, speed_rpm=2.0, torque_nm=2.0, ambient_c=2.0)
        )  # duplicate id
    with (
        pytest.raises(RecordNotFoundError, match="identifications: no id 42"),
        repo.session_scope(factory) as s,
    ):
        repo.get_identification(s, 42)
    with pytest.raises(RecordNotFoundError, match="conditions: no id 42"), repo.session_scope(factory) as s:
        repo.end_condition(s, ConditionEnd(42, T0))


def test_pagination_and_time_filter(factory: sessionmaker[Session]) -> None:
    add_condition(factory, 1, (3000.0, 8.0, 23.2), T0)
    finished = {i: T0 + timedelta(minutes=7 * i) for i in range(1, 26)}
    with repo.session_scope(factory) as s:
        repo.write_records(s, [ident(i, 1, t) for i, t in finished.items()])
    seen: list[int] = []
    with repo.session_scope(factory) as s:
        for offset in (0, 10, 20, 30):
            page = repo.list_identifications(s, limit=10, offset=offset)
            assert page.total == 25 and (page.limit, page.offset) == (10, offset)
            seen += [r.id for r in page.items]
    assert seen == sorted(finished, key=lambda i: finished[i], reverse=True)  # newest first, no gaps/dupes
    since, until = finished[5], finished[12]  # [since, until): 5..11 inclusive
    expected = sorted((i for i, t in finished.items() if since <= t < until), reverse=True)
    with repo.session_scope(factory) as s:
        page = repo.list_identifications(s, since=since.astimezone(CEST), until=until, limit=100)
    assert [r.id for r in page.items] == expected and page.total == len(expected)
    with pytest.raises(ValueError, match="limit"), repo.session_scope(factory) as s:
        repo.list_identifications(s, limit=0)


def test_latest_per_condition_last_and_max_ids(factory: sessionmaker[Session]) -> None:
    add_condition(factory, 1, (3000.0, 10.0, 22.0), T0)
    add_condition(factory, 2, (4000.0, 10.0, 22.0), T0 + timedelta(hours=2))
    records = [
        ident(1, 1, T0 + timedelta(minutes=10)),
        ident(2, 1, T0 + timedelta(minutes=20)),
        ident(3, 2, T0 + timedelta(hours=2, minutes=10)),
        ident(4, 2, T0 + timedelta(hours=2, minutes=20), outcome="cancelled", h=None),
    ]
    with repo.session_scope(factory) as s:
        repo.write_records(s, [*records, ConditionEnd(1, T0 + timedelta(hours=2))])
    with repo.session_scope(factory) as s:
        assert [r.id for r in repo.latest_per_condition(s)] == [3, 2]
        assert [r.id for r in repo.latest_per_condition(s, limit=1)] == [3]
        last = repo.last_identification(s)
        assert last is not None and last.id == 3
        assert repo.max_ids(s) == (2, 4)
        assert repo.get_condition(s, 1).ended_at == T0 + timedelta(hours=2)
        conds = repo.list_conditions(s, limit=1)
        assert conds.total == 2 and [c.id for c in conds.items] == [2]
        assert [r.id for r in repo.list_identifications(s, condition_id=1).items] == [2, 1]


def test_device_event_filters_and_sample_window(factory: sessionmaker[Session]) -> None:
    events = [
        DeviceEventData(t=T0 + timedelta(seconds=i), device="modbus" if i % 2 else "can", kind=f"k{i}")
        for i in range(10)
    ]
    samples = [
        SampleData(
            t=T0 + timedelta(seconds=10 * i),
            temps_c=[20.0 + i] * 32,
            ambient_c=22.0,
            speed_rpm=4000.0,
            torque_nm=10.0,
            quality=["ok"] * 32,
        )
        for i in range(20)
    ]
    with repo.session_scope(factory) as s:
        repo.write_records(s, [*events, *samples])
    with repo.session_scope(factory) as s:
        modbus = repo.list_device_events(s, device="modbus", limit=3)
        assert modbus.total == 5 and [e.kind for e in modbus.items] == ["k9", "k7", "k5"]
        window = repo.list_samples(s, since=T0 + timedelta(seconds=50), until=T0 + timedelta(seconds=100))
        assert [r.temps_c[0] for r in window] == [25.0, 26.0, 27.0, 28.0, 29.0]
        assert repo.count_rows(s, SampleRow) == 20 and repo.count_rows(s, Condition) == 0
        assert repo.count_rows(s, Identification) == 0
