"""Revision 0009 (``probe_measurements.offset_step``): a reading stored by 0008 stays readable and reads as
not a step of the fixture offset (it replays into the offset model as an ordinary reading); downgrade drops
the column and keeps the row."""

from __future__ import annotations

from datetime import UTC, datetime

import sqlalchemy as sa

from service.host.persistence import restore
from service.store import migrate
from service.store.engine import create_db_engine, make_session_factory

AT = datetime(2026, 11, 27, 8, 0, tzinfo=UTC)


def _old_row(conn: sa.Connection) -> None:
    table = sa.Table("probe_measurements", sa.MetaData(), autoload_with=conn)
    assert "offset_step" not in table.c
    conn.execute(
        sa.insert(table),
        [
            {
                "at": AT,
                "recorded_at": AT,
                "axial_um": 4.5,
                "sd_um": 1.0,
                "features": [1.5, 7.25, -2.0, 0.5, -1.0, -2.75],
                "field_var_um2": 0.04,
                "predicted_um": 4.2,
                "sigma_um": 1.1,
                "innovation_um": 0.3,
                "accepted": True,
                "set_by": "plc",
                "source": "api",
                "spindle_id": "spindle1",
            }
        ],
    )


def test_0009_reads_an_older_reading_as_no_offset_step(db_url: str) -> None:
    eng = create_db_engine(db_url)
    try:
        migrate.upgrade(eng, "0008")
        with eng.begin() as conn:
            _old_row(conn)
        migrate.upgrade(eng)
        got = restore(make_session_factory(eng, spindle_id="spindle1")).probes
        assert len(got) == 1 and got[0].accepted and got[0].offset_step is False
        assert got[0].axial_um == 4.5
        migrate.downgrade(eng, "0008")
        with eng.connect() as conn:
            assert conn.execute(sa.text("SELECT count(*) FROM probe_measurements")).scalar_one() == 1
    finally:
        eng.dispose()
