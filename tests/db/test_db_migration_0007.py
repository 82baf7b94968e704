"""Migration 0007 on a database holding 0006 data: every row kept (counted), stamped with the spindle id;
the speed map's covariance moved; PostgreSQL partitions made and ignored by autogenerate."""

from __future__ import annotations

import json
from datetime import UTC, datetime, timedelta

import sqlalchemy as sa
from alembic.autogenerate import compare_metadata
from alembic.migration import MigrationContext

from service.host.persistence import restore
from service.store import migrate
from service.store import repository as repo
from service.store.engine import create_db_engine, make_session_factory
from service.store.models import Base, SampleRow
from service.store.partitions import list_partitions

T0 = datetime(2026, 3, 1, 23, 30, tzinfo=UTC)  # the samples span two UTC days
N_SAMPLES = 240  # 10-s samples: 40 min, the last 10 on the next day
OLD_TABLES = {
    "conditions": 3,
    "identifications": 4,
    "device_events": 5,
    "samples": N_SAMPLES,
    "offset_calibrations": 2,
    "compensation_references": 2,
    "live_state": 1,
    "mechanics_calibrations": 1,
    "probe_measurements": 3,
}


def _rows(conn: sa.Connection, name: str, n: int) -> None:
    t = sa.table(name, *(sa.column(c.name, c.type) for c in _old_columns(conn, name)))
    conn.execute(t.insert(), [_row(name, i) for i in range(n)])


def _old_columns(conn: sa.Connection, name: str) -> list[sa.Column]:
    return list(sa.Table(name, sa.MetaData(), autoload_with=conn).columns)


def _row(name: str, i: int) -> dict[str, object]:
    t = T0 + timedelta(seconds=10 * i)
    common = {"id": i + 1}
    if name == "conditions":
        return common | {
            "started_at": t,
            "ended_at": None,
            "speed_rpm": 3000.0 + i,
            "torque_nm": 8.0,
            "ambient_c": 22.0,
        }
    if name == "identifications":
        diag = {"at_bound": [False] * 7}
        method = "hybrid"
        if i >= 2:  # two speed-map fits, each with its covariance
            method = "speed-map"
            diag["speed_map"] = {
                "family": "nodes",
                "mean": [float(i)] * 3,
                "cov_upper_b64": "AAAA" * 100,
                "visited_rpm": [],
                "visited_s": [],
                "fitted_at": t.isoformat(),
                "rmse_c": 0.1,
            }
        return common | {
            "condition_id": 1 + i % 3,
            "started_at": t,
            "finished_at": t,
            "window_start": t,
            "window_end": t,
            "reason": "schedule",
            "outcome": "ok",
            "message": "",
            "method": method,
            "model_version": "m",
            **{f"h{k}": 50.0 + i for k in range(1, 8)},
            "nfev": 3,
            "duration_s": 0.5,
            "n_sensors_used": 32,
            "diagnostics": diag,
        }
    if name == "device_events":
        return common | {"t": t, "device": "can", "kind": "gap", "detail": str(i)}
    if name == "samples":
        temps = [20.0 + 0.01 * i + c for c in range(32)]
        temps[3] = None
        return common | {
            "t": t,
            "ambient_c": 22.0,
            "speed_rpm": 3000.0,
            "torque_nm": 8.0,
            "temps_c": temps,
            "n_good": 31,
            "bad_channels": {"4": "open_circuit"},
            "can_ok": True,
            "daq_ok": True,
        }
    if name == "offset_calibrations":
        return common | {
            "t_from": t,
            "t_to": t,
            "source": "auto",
            "samples": 30,
            "offsets_c": [0.1] * 32,
            "sd_c": [0.01] * 32,
        }
    if name == "compensation_references":
        return common | {"at": t, "temperature_c": 21.0, "sd_c": 0.1, "source": "api", "set_by": "x"}
    if name == "live_state":
        return common | {
            "at": t,
            "model_version": "m",
            "converged": True,
            "ambient_c": 22.0,
            "speed_rpm": 1.0,
            "torque_nm": 1.0,
            "payload": b"npz",
        }
    if name == "mechanics_calibrations":
        return common | {
            "at": t,
            "set_by": "x",
            "source": "cli",
            "restraint": 0.5,
            "alpha_shaft": 1.0,
            "alpha_housing": 1.0,
            "cov": [0.0] * 9,
            "residual_rms_um": 0.4,
            "residual_max_um": 2.0,
            "explained": True,
            "temperatures_sha256": "a",
            "canlog_sha256": None,
            "displacements_sha256": "b",
            "report": {},
        }
    assert name == "probe_measurements"
    return common | {
        "at": t,
        "recorded_at": t,
        "axial_um": 1.0,
        "sd_um": 0.5,
        "features": [0.0] * 6,
        "field_var_um2": 1.0,
        "predicted_um": 1.0,
        "sigma_um": 1.0,
        "innovation_um": 0.0,
        "accepted": True,
        "set_by": "x",
        "source": "api",
    }


def test_0007_keeps_every_row_of_a_0006_database_and_stamps_the_spindle(db_url: str) -> None:
    eng = create_db_engine(db_url)
    try:
        migrate.upgrade(eng, "0006")
        with eng.begin() as conn:
            for name, n in OLD_TABLES.items():
                _rows(conn, name, n)
        migrate.upgrade(eng, spindle_id="line3-spindle7")
        with eng.connect() as conn:
            for name, n in OLD_TABLES.items():
                got = conn.execute(
                    sa.text(f"SELECT spindle_id, count(*) FROM {name} GROUP BY spindle_id")
                ).all()
                assert [tuple(r) for r in got] == [("line3-spindle7", n)], name
            assert conn.execute(sa.text("SELECT id FROM spindles")).scalars().all() == ["line3-spindle7"]
            diags = (
                conn.execute(sa.text("SELECT diagnostics FROM identifications ORDER BY id")).scalars().all()
            )
            maps = [(json.loads(d) if isinstance(d, str) else d).get("speed_map") for d in diags]
            assert maps[:2] == [None, None] and all("cov_upper_b64" not in m for m in maps[2:])
            state = conn.execute(sa.text("SELECT identification_id, state FROM speed_map_state")).one()
            stored = json.loads(state[1]) if isinstance(state[1], str) else state[1]
            assert state[0] == 4 and stored["cov_upper_b64"] == "AAAA" * 100
            if eng.dialect.name == "postgresql":
                days = [d for _, d in list_partitions(conn)]
                assert days == [T0.date(), T0.date() + timedelta(days=1)]
                unfiltered = compare_metadata(MigrationContext.configure(conn), Base.metadata)
                assert {d[1].name for d in unfiltered if d[0] == "remove_table"} == {
                    "samples_p20260301",
                    "samples_p20260302",
                }
            ctx = MigrationContext.configure(
                conn, opts={"compare_type": True, "include_object": _env_filter()}
            )
            assert compare_metadata(ctx, Base.metadata) == []
        factory = make_session_factory(eng, spindle_id="line3-spindle7")
        with repo.session_scope(factory) as s:
            rows = repo.list_samples(s)
            assert len(rows) == N_SAMPLES and rows[7].temps_c[:5] == [20.07, 21.07, 22.07, None, 24.07]
            assert repo.count_rows(s, SampleRow) == N_SAMPLES
            repo.write_records(s, [])  # new rows go on after the old ids
            ev = repo.add_device_event(s, _event())
            assert ev.id == OLD_TABLES["device_events"] + 1
        assert restore(factory).next_identification_id == 5
    finally:
        eng.dispose()


def _event():  # type: ignore[no-untyped-def]
    from service.contracts.records import DeviceEventData

    return DeviceEventData(t=T0, device="db", kind="after")


def _env_filter():  # type: ignore[no-untyped-def]
    """The ``include_object`` of ``service/migrations/env.py`` (it runs only inside Alembic)."""
    import importlib.util

    from service.store.migrate import MIGRATIONS_DIR

    source = (MIGRATIONS_DIR / "env.py").read_text()
    start = source.index("PARTITION = ")
    end = source.index("def _configure")
    scope: dict[str, object] = {}
    exec("import re\n" + source[start:end], scope)
    assert importlib.util is not None
    return scope["include_object"]


def test_downgrade_below_0007_keeps_one_spindles_rows(db_url: str) -> None:
    from tests.db.test_db_spindles import fill

    eng = create_db_engine(db_url)
    try:
        migrate.upgrade(eng)
        from tests.db.conftest import spindle_factory

        fill(spindle_factory(eng, "a"), base=20.0, h1=81.0)
        fill(spindle_factory(eng, "b"), base=30.0, h1=91.0)
        migrate.downgrade(eng, "0006", spindle_id="b")
        with eng.connect() as conn:
            counts = {
                t: conn.execute(sa.text(f"SELECT count(*) FROM {t}")).scalar()
                for t in ("conditions", "identifications", "device_events", "samples", "live_state")
            }
            assert counts == {
                "conditions": 2,
                "identifications": 1,
                "device_events": 1,
                "samples": 30,
                "live_state": 1,
            }
            assert conn.execute(sa.text("SELECT h1 FROM identifications")).scalar() == 91.0
            assert "spindles" not in sa.inspect(conn).get_table_names()
        migrate.upgrade(eng, spindle_id="b")  # and back, the rows kept
        with repo.session_scope(make_session_factory(eng, spindle_id="b")) as s:
            assert repo.count_rows(s, SampleRow) == 30 and repo.get_identification(s, 1).h[0] == 91.0
    finally:
        eng.dispose()
