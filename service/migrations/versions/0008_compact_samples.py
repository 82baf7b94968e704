"""compact samples: centi-degree smallint[] temperatures, real scalars, bytea qualities, aligned columns
(issue 29: storage per spindle-day <= 3 MB)

PostgreSQL only (SQLite keeps its JSON arrays and doubles: the column types differ there by design,
``service.store.types``; nothing to convert). ``samples`` (partitioned by day) and ``samples_1min`` are
rebuilt: renamed ``*_old`` (with their partitions and their indexes, whose names are schema-wide), created in
the new shape, every row copied in one statement, the old dropped. New layout, fixed widths first by
alignment, then the variable-length columns::

    samples      t, speed_rpm real, torque_nm real, ambient_c real, n_good smallint, can_ok, daq_ok,
                 temps_c smallint[] (centi-degrees), bad_channels bytea, spindle_id
    samples_1min t, ambient_c, speed_rpm, torque_nm, speed_max_rpm (real), n, n_good_min smallint, can_ok,
                 daq_ok, temps_c smallint[], spindle_id

Conversions: a temperature becomes ``round(°C × 100)``; one beyond int16 (outside −327.68…327.67 °C) or NaN
becomes NULL (no usable value), like the application's ``centi_celsius``. ``bad_channels`` ``{"7":
"open_circuit"}`` becomes the bytes (7, 2): channel, code of the ``drivers.quality.Quality`` labels as of this
revision (copied below: a migration never imports application code); an unknown label or a channel outside
1–255 stops the migration before anything is changed, naming it. Doubles become ``real`` (float32).

Downgrade converts back (centi-degrees / 100 as ``real``, the bytes to JSON, ``real`` to double precision
through its shortest decimal, 22.01 not 22.0100002…): what the upgrade rounded stays rounded.

Written by hand. Revision ID: 0008, Revises: 0007
Create Date: 2026-11-28 02:30:00 UTC
"""

from __future__ import annotations

import re
from datetime import UTC, date, datetime, timedelta
from typing import Any

import sqlalchemy as sa
from alembic import op
from sqlalchemy.dialects import postgresql

revision = "0008"
down_revision = "0007"
branch_labels = None
depends_on = None

SPINDLE_LEN = 64
QUALITY_CODES = {  # drivers.quality.Quality as of 0008 (OK = 0 is never stored)
    "stale": 1,
    "open_circuit": 2,
    "out_of_range": 3,
    "nan": 4,
    "stuck": 5,
    "no_data": 6,
    "fault": 7,
}
PART = re.compile(r"^samples_p(\d{8})$")


def _pg() -> bool:
    return bool(op.get_bind().dialect.name == "postgresql")


def upgrade() -> None:
    if not _pg():
        return
    _check_qualities()
    days = _retire_samples()
    _create_samples(compact=True, days=days)
    temps = (
        "ARRAY(SELECT CASE WHEN round(e.v::float8 * 100) BETWEEN -32768 AND 32767 "
        "THEN round(e.v::float8 * 100)::smallint END "
        "FROM unnest(temps_c) WITH ORDINALITY AS e(v, i) ORDER BY e.i)::smallint[]"
    )
    codes = " ".join(f"WHEN '{label}' THEN {code}" for label, code in QUALITY_CODES.items())
    bad = (
        "(SELECT COALESCE(string_agg(set_byte(set_byte('\\x0000'::bytea, 0, j.k::int), 1, "
        f"CASE j.v {codes} END), ''::bytea ORDER BY j.k::int), ''::bytea) "
        "FROM json_each_text(bad_channels) AS j(k, v))"
    )
    _copy(
        "samples",
        [
            "t",
            "speed_rpm",
            "torque_nm",
            "ambient_c",
            "n_good",
            "can_ok",
            "daq_ok",
            "temps_c",
            "bad_channels",
            "spindle_id",
        ],
        [
            "t",
            "speed_rpm::real",
            "torque_nm::real",
            "ambient_c::real",
            "n_good::smallint",
            "can_ok",
            "daq_ok",
            temps,
            bad,
            "spindle_id",
        ],
    )
    op.execute('DROP TABLE "samples_old" CASCADE')
    _retire_minutes()
    _create_minutes(compact=True)
    _copy(
        "samples_1min",
        [
            "t",
            "ambient_c",
            "speed_rpm",
            "torque_nm",
            "speed_max_rpm",
            "n",
            "n_good_min",
            "can_ok",
            "daq_ok",
            "temps_c",
            "spindle_id",
        ],
        [
            "t",
            "ambient_c::real",
            "speed_rpm::real",
            "torque_nm::real",
            "speed_max_rpm::real",
            "n",
            "n_good_min::smallint",
            "can_ok",
            "daq_ok",
            temps,
            "spindle_id",
        ],
    )
    op.drop_table("samples_1min_old")


def downgrade() -> None:
    if not _pg():
        return
    days = _retire_samples()
    _create_samples(compact=False, days=days)
    temps = (
        "ARRAY(SELECT (e.v::float8 / 100)::real FROM unnest(temps_c) WITH ORDINALITY AS e(v, i) "
        "ORDER BY e.i)::real[]"
    )
    labels = " ".join(f"WHEN {code} THEN '{label}'" for label, code in QUALITY_CODES.items())
    bad = (
        "(SELECT COALESCE(json_object_agg(get_byte(bad_channels, 2 * i)::text, "
        f"CASE get_byte(bad_channels, 2 * i + 1) {labels} END ORDER BY i), '{{}}'::json) "
        "FROM generate_series(0, length(bad_channels) / 2 - 1) AS i)"
    )
    _copy(
        "samples",
        [
            "t",
            "ambient_c",
            "speed_rpm",
            "torque_nm",
            "temps_c",
            "n_good",
            "bad_channels",
            "can_ok",
            "daq_ok",
            "spindle_id",
        ],
        [
            "t",
            "ambient_c::text::float8",
            "speed_rpm::text::float8",
            "torque_nm::text::float8",
            temps,
            "n_good::int",
            bad,
            "can_ok",
            "daq_ok",
            "spindle_id",
        ],
    )
    op.execute('DROP TABLE "samples_old" CASCADE')
    _retire_minutes()
    _create_minutes(compact=False)
    _copy(
        "samples_1min",
        [
            "t",
            "n",
            "ambient_c",
            "speed_rpm",
            "torque_nm",
            "speed_max_rpm",
            "temps_c",
            "n_good_min",
            "can_ok",
            "daq_ok",
            "spindle_id",
        ],
        [
            "t",
            "n",
            "ambient_c::text::float8",
            "speed_rpm::text::float8",
            "torque_nm::text::float8",
            "speed_max_rpm::text::float8",
            temps,
            "n_good_min::int",
            "can_ok",
            "daq_ok",
            "spindle_id",
        ],
    )
    op.drop_table("samples_1min_old")


def _check_qualities() -> None:
    """Refuse (before any change) labels and channels the bytes cannot hold."""
    conn = op.get_bind()
    rows = conn.execute(
        sa.text("SELECT DISTINCT j.k, j.v FROM samples, json_each_text(bad_channels) AS j(k, v)")
    ).all()
    for key, label in rows:
        if label not in QUALITY_CODES:
            raise RuntimeError(
                f"samples.bad_channels: unknown quality {label!r} (channel {key}); known: "
                f"{sorted(QUALITY_CODES)}"
            )
        if not (key.isdigit() and 1 <= int(key) <= 255):
            raise RuntimeError(f"samples.bad_channels: channel {key!r} is not a number in 1..255")


def _retire_samples() -> list[date]:
    """Rename ``samples``, its key and every partition (with its indexes) out of the way; the days to make
    partitions for in the new table (every old partition's and every day holding rows)."""
    conn = op.get_bind()
    parts = (
        conn.execute(
            sa.text(
                "SELECT c.relname FROM pg_inherits i JOIN pg_class c ON c.oid = i.inhrelid "
                "WHERE i.inhparent = 'samples'::regclass"
            )
        )
        .scalars()
        .all()
    )
    days = {datetime.strptime(m.group(1), "%Y%m%d").date() for p in parts if (m := PART.match(p))}
    days |= {r[0] for r in conn.execute(sa.text("SELECT DISTINCT (t AT TIME ZONE 'UTC')::date FROM samples"))}
    for part in parts:
        indexes = (
            conn.execute(
                sa.text(
                    "SELECT c.relname FROM pg_index x JOIN pg_class c ON c.oid = x.indexrelid "
                    "WHERE x.indrelid = CAST(:p AS regclass)"
                ),
                {"p": f'"{part}"'},
            )
            .scalars()
            .all()
        )
        for ix in indexes:
            op.execute(f'ALTER INDEX "{ix}" RENAME TO "{ix}_old"')
        op.execute(f'ALTER TABLE "{part}" RENAME TO "{part}_old"')
    op.execute('ALTER TABLE "samples" RENAME CONSTRAINT "pk_samples" TO "pk_samples_old"')
    op.rename_table("samples", "samples_old")
    return sorted(days)


def _retire_minutes() -> None:
    op.execute('ALTER TABLE "samples_1min" RENAME CONSTRAINT "pk_samples_1min" TO "pk_samples_1min_old"')
    op.rename_table("samples_1min", "samples_1min_old")


def _scalar(compact: bool) -> sa.types.TypeEngine[float]:
    return sa.REAL() if compact else sa.Double()


def _temps(compact: bool) -> sa.types.TypeEngine[Any]:
    return postgresql.ARRAY(sa.SmallInteger() if compact else sa.REAL())


def _create_samples(*, compact: bool, days: list[date]) -> None:
    f = _scalar(compact)
    scalars = [sa.Column(n, f, nullable=True) for n in ("speed_rpm", "torque_nm", "ambient_c")]
    flags: list[sa.Column[Any]] = [
        sa.Column("can_ok", sa.Boolean(), nullable=False),
        sa.Column("daq_ok", sa.Boolean(), nullable=False),
    ]
    if compact:
        cols: list[sa.Column[Any]] = [
            *scalars,
            sa.Column("n_good", sa.SmallInteger(), nullable=False),
            *flags,
            sa.Column("temps_c", _temps(True), nullable=False),
            sa.Column("bad_channels", sa.LargeBinary(), nullable=False),
        ]
    else:  # 0007's order
        cols = [
            scalars[2],
            scalars[0],
            scalars[1],
            sa.Column("temps_c", _temps(False), nullable=False),
            sa.Column("n_good", sa.Integer(), nullable=False),
            sa.Column("bad_channels", sa.JSON(), nullable=False),
            *flags,
        ]
    op.create_table(
        "samples",
        sa.Column("t", sa.DateTime(timezone=True), nullable=False),
        *cols,
        sa.Column("spindle_id", sa.String(length=SPINDLE_LEN), nullable=False),
        sa.PrimaryKeyConstraint("spindle_id", "t", name="pk_samples"),
        sa.ForeignKeyConstraint(["spindle_id"], ["spindles.id"], name="fk_samples_spindle_id_spindles"),
        postgresql_partition_by="RANGE (t)",
    )
    for d in days:
        lo = datetime(d.year, d.month, d.day, tzinfo=UTC)
        hi = lo + timedelta(days=1)
        op.execute(
            f'CREATE TABLE "samples_p{d:%Y%m%d}" PARTITION OF samples '
            f"FOR VALUES FROM ('{lo.isoformat()}') TO ('{hi.isoformat()}')"
        )


def _create_minutes(*, compact: bool) -> None:
    f = _scalar(compact)
    scalars = [
        sa.Column(n, f, nullable=True) for n in ("ambient_c", "speed_rpm", "torque_nm", "speed_max_rpm")
    ]
    flags: list[sa.Column[Any]] = [
        sa.Column("can_ok", sa.Boolean(), nullable=False),
        sa.Column("daq_ok", sa.Boolean(), nullable=False),
    ]
    n = sa.Column("n", sa.Integer(), nullable=False)
    if compact:
        cols: list[sa.Column[Any]] = [
            *scalars,
            n,
            sa.Column("n_good_min", sa.SmallInteger(), nullable=False),
            *flags,
            sa.Column("temps_c", _temps(True), nullable=False),
        ]
    else:  # 0007's order
        cols = [
            n,
            *scalars,
            sa.Column("temps_c", _temps(False), nullable=False),
            sa.Column("n_good_min", sa.Integer(), nullable=False),
            *flags,
        ]
    op.create_table(
        "samples_1min",
        sa.Column("t", sa.DateTime(timezone=True), nullable=False),
        *cols,
        sa.Column("spindle_id", sa.String(length=SPINDLE_LEN), nullable=False),
        sa.PrimaryKeyConstraint("spindle_id", "t", name="pk_samples_1min"),
        sa.ForeignKeyConstraint(["spindle_id"], ["spindles.id"], name="fk_samples_1min_spindle_id_spindles"),
    )


def _copy(name: str, columns: list[str], exprs: list[str]) -> None:
    cols = ", ".join(f'"{c}"' for c in columns)
    op.execute(sa.text(f'INSERT INTO "{name}" ({cols}) SELECT {", ".join(exprs)} FROM "{name}_old"'))
