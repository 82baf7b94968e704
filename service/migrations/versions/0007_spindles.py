"""spindles: a spindle id in every row, composite keys, BIGINT ids, partitioned samples, minute means,
the speed map's newest state in its own table (issue 29 items 1-3)

Every table is rebuilt (renamed to ``*_old``, created in its new shape, its rows copied, the old one dropped),
which works the same on SQLite (no ALTER of keys there) and PostgreSQL, keeps every row and stamps it with
the spindle id: ``config.attributes["spindle_id"]`` (``service.store.migrate.upgrade(..., spindle_id=)``), else
``CHTC_SPINDLE__ID``, else ``spindle1``. Samples stored twice at the same instant (a retried batch, possible
before this revision) become one row: the new key is ``(spindle_id, t)``.

On PostgreSQL ``samples`` becomes a table partitioned by day on ``t`` (``samples_pYYYYMMDD``, bounds in UTC);
the partitions holding the copied rows are created here, later ones by the service
(``service.store.partitions``). Temperatures become ``real[]`` there.

Successful speed-map fits keep their map in the identification's diagnostics without the covariance; the
newest map with its covariance goes to ``speed_map_state``.

Downgrade keeps the rows of that one spindle (the others are dropped: restore a backup to go back with
several spindles); the speed maps' covariances stay in ``speed_map_state``'s one row and are lost.

Written by hand; never imports application code. Revision ID: 0007, Revises: 0006
Create Date: 2026-11-28 00:10:00 UTC
"""

from __future__ import annotations

import json
import os
from collections.abc import Sequence
from datetime import UTC, date, datetime, timedelta
from typing import Any

import sqlalchemy as sa
from alembic import context, op
from sqlalchemy.dialects import postgresql
from sqlalchemy.schema import SchemaItem

revision = "0007"
down_revision = "0006"
branch_labels = None
depends_on = None

SPINDLE_LEN = 64
BIG_ID = sa.BigInteger().with_variant(sa.Integer(), "sqlite")
# (table, new primary key, new indexes (besides), has a database id)
TABLES: list[tuple[str, tuple[str, ...], list[tuple[str, ...]]]] = [
    ("conditions", ("spindle_id", "id"), [("spindle_id", "started_at")]),
    ("identifications", ("spindle_id", "id"), [("spindle_id", "finished_at"), ("spindle_id", "condition_id")]),
    ("device_events", ("id",), [("spindle_id", "t")]),
    ("samples", ("spindle_id", "t"), []),
    ("offset_calibrations", ("id",), [("spindle_id", "t_to")]),
    ("compensation_references", ("id",), [("spindle_id", "at")]),
    ("live_state", ("id",), [("spindle_id",)]),
    ("mechanics_calibrations", ("id",), [("spindle_id", "at")]),
    ("probe_measurements", ("id",), [("spindle_id", "at")]),
]
OLD_INDEXES = {  # 0001-0006
    "conditions": [("started_at",)],
    "identifications": [("condition_id",), ("finished_at",)],
    "device_events": [("t",)],
    "samples": [("t",)],
    "offset_calibrations": [("t_to",)],
    "compensation_references": [("at",)],
    "live_state": [],
    "mechanics_calibrations": [("at",)],
    "probe_measurements": [("at",)],
}
COND_FK = "fk_identifications_spindle_id_conditions"


def _spindle_id() -> str:
    sid = context.config.attributes.get("spindle_id") or os.environ.get("CHTC_SPINDLE__ID") or "spindle1"
    return str(sid)


def _pg() -> bool:
    return bool(op.get_bind().dialect.name == "postgresql")


def _ix(table: str, cols: Sequence[str]) -> str:
    return f"ix_{table}_{'_'.join(cols)}"


def _portable(col: sa.Column, *, serial: bool) -> sa.Column:
    """A reflected column, as the models declare it (aware timestamps, BIGINT database ids)."""
    typ = col.type
    if isinstance(typ, sa.DateTime):
        typ = sa.DateTime(timezone=True)
    elif isinstance(typ, sa.JSON):
        typ = sa.JSON()
    elif col.name == "id":
        typ = BIG_ID if serial else sa.BigInteger()
    return sa.Column(col.name, typ, nullable=col.nullable, autoincrement=serial if col.name == "id" else "auto")


def _retire(name: str, *, had_id_seq: bool, pk_old: str, fk_old: Sequence[str]) -> sa.Table:
    """Rename ``name`` to ``name_old`` (with its constraint, index and sequence names, which PostgreSQL keeps
    schema-wide); returns the old table, reflected."""
    conn = op.get_bind()
    old = sa.Table(name, sa.MetaData(), autoload_with=conn)
    for ix in old.indexes:
        op.drop_index(str(ix.name), table_name=name)
    if _pg():
        op.execute(f'ALTER TABLE "{name}" RENAME CONSTRAINT "{pk_old}" TO "{pk_old}_old"')
        for fk in fk_old:
            op.execute(f'ALTER TABLE "{name}" RENAME CONSTRAINT "{fk}" TO "{fk}_old"')
        if had_id_seq:
            op.execute(f'ALTER SEQUENCE IF EXISTS "{name}_id_seq" RENAME TO "{name}_id_seq_old"')
    op.rename_table(name, f"{name}_old")
    return old


def _copy(name: str, columns: Sequence[str], exprs: Sequence[str], *, where: str = "", ignore: bool) -> None:
    cols = ", ".join(f'"{c}"' for c in columns)
    sel = ", ".join(exprs)
    if ignore and not _pg():
        head = f'INSERT OR IGNORE INTO "{name}" ({cols})'
    else:
        head = f'INSERT INTO "{name}" ({cols})'
    tail = " ON CONFLICT DO NOTHING" if ignore and _pg() else ""
    op.execute(sa.text(f'{head} SELECT {sel} FROM "{name}_old" {where}{tail}'))


def _reset_sequence(name: str) -> None:
    if _pg():
        op.execute(
            f"SELECT setval(pg_get_serial_sequence('\"{name}\"', 'id'), COALESCE(MAX(id), 0) + 1, false) "
            f'FROM "{name}"'
        )


def _partition_days(days: Sequence[date]) -> None:
    for d in sorted(set(days)):
        lo = datetime(d.year, d.month, d.day, tzinfo=UTC)
        hi = lo + timedelta(days=1)
        op.execute(
            f'CREATE TABLE IF NOT EXISTS "samples_p{d:%Y%m%d}" PARTITION OF samples '
            f"FOR VALUES FROM ('{lo.isoformat()}') TO ('{hi.isoformat()}')"
        )


def upgrade() -> None:
    sid = _spindle_id()
    op.create_table(
        "spindles",
        sa.Column("id", sa.String(length=SPINDLE_LEN), nullable=False),
        sa.Column("description", sa.Text(), nullable=False),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.PrimaryKeyConstraint("id", name="pk_spindles"),
    )
    spindles = sa.table(
        "spindles", sa.column("id"), sa.column("description"), sa.column("created_at", sa.DateTime(True))
    )
    op.execute(spindles.insert().values(id=sid, description="", created_at=datetime.now(UTC)))
    for name, pk, indexes in TABLES:
        _upgrade_table(name, pk, indexes, sid)
    for name, *_ in reversed(TABLES):  # children first (identifications_old refers to conditions_old)
        op.drop_table(f"{name}_old")
    _create_minutes()
    _create_speed_map_state()
    _move_speed_map_covariances(sid)


def _upgrade_table(name: str, pk: tuple[str, ...], indexes: list[tuple[str, ...]], sid: str) -> None:
    serial = pk == ("id",)
    old = _retire(
        name,
        had_id_seq=name != "conditions" and name != "identifications",
        pk_old=f"pk_{name}",
        fk_old=["fk_identifications_condition_id_conditions"] if name == "identifications" else [],
    )
    cols = [_portable(c, serial=serial) for c in old.columns if not (name == "samples" and c.name == "id")]
    if name == "samples" and _pg():
        cols = [sa.Column("temps_c", postgresql.ARRAY(sa.REAL()), nullable=False) if c.name == "temps_c" else c
                for c in cols]
    names = [c.name for c in cols]
    extra: list[SchemaItem] = []
    if name == "identifications":
        extra.append(
            sa.ForeignKeyConstraint(
                ["spindle_id", "condition_id"], ["conditions.spindle_id", "conditions.id"],
                name=COND_FK, ondelete="CASCADE",
            )
        )
    kw: dict[str, Any] = {"postgresql_partition_by": "RANGE (t)"} if name == "samples" else {}
    op.create_table(
        name,
        *cols,
        sa.Column("spindle_id", sa.String(length=SPINDLE_LEN), nullable=False),
        sa.PrimaryKeyConstraint(*pk, name=f"pk_{name}"),
        sa.ForeignKeyConstraint(["spindle_id"], ["spindles.id"], name=f"fk_{name}_spindle_id_spindles"),
        *extra,
        **kw,
    )
    for ix in indexes:
        op.create_index(_ix(name, ix), name, list(ix), unique=False)
    exprs = [f'"{n}"' for n in names]
    if name == "samples" and _pg():
        days = op.get_bind().execute(sa.text("SELECT DISTINCT (t AT TIME ZONE 'UTC')::date FROM samples_old"))
        _partition_days([r[0] for r in days])
        exprs[names.index("temps_c")] = (
            "ARRAY(SELECT e.v::real FROM json_array_elements_text(temps_c) WITH ORDINALITY AS e(v, i) "
            "ORDER BY e.i)"
        )
    _copy(name, [*names, "spindle_id"], [*exprs, f"'{sid}'"], ignore=name == "samples")
    if serial:
        _reset_sequence(name)


def _create_minutes() -> None:
    temps = sa.JSON().with_variant(postgresql.ARRAY(sa.REAL()), "postgresql")
    op.create_table(
        "samples_1min",
        sa.Column("t", sa.DateTime(timezone=True), nullable=False),
        sa.Column("n", sa.Integer(), nullable=False),
        sa.Column("ambient_c", sa.Double(), nullable=True),
        sa.Column("speed_rpm", sa.Double(), nullable=True),
        sa.Column("torque_nm", sa.Double(), nullable=True),
        sa.Column("speed_max_rpm", sa.Double(), nullable=True),
        sa.Column("temps_c", temps, nullable=False),
        sa.Column("n_good_min", sa.Integer(), nullable=False),
        sa.Column("can_ok", sa.Boolean(), nullable=False),
        sa.Column("daq_ok", sa.Boolean(), nullable=False),
        sa.Column("spindle_id", sa.String(length=SPINDLE_LEN), nullable=False),
        sa.PrimaryKeyConstraint("spindle_id", "t", name="pk_samples_1min"),
        sa.ForeignKeyConstraint(["spindle_id"], ["spindles.id"], name="fk_samples_1min_spindle_id_spindles"),
    )


def _create_speed_map_state() -> None:
    op.create_table(
        "speed_map_state",
        sa.Column("identification_id", sa.BigInteger(), nullable=False),
        sa.Column("fitted_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("state", sa.JSON(), nullable=False),
        sa.Column("spindle_id", sa.String(length=SPINDLE_LEN), nullable=False),
        sa.PrimaryKeyConstraint("spindle_id", name="pk_speed_map_state"),
        sa.ForeignKeyConstraint(
            ["spindle_id"], ["spindles.id"], name="fk_speed_map_state_spindle_id_spindles"
        ),
    )


COV_KEYS = ("cov_upper_b64", "cov")


def _move_speed_map_covariances(sid: str) -> None:
    """The newest successful map fit's whole map to ``speed_map_state``; every history row's map without its
    covariance (the 18.6 kB per row that were never read again)."""
    ident = sa.table(
        "identifications",
        sa.column("spindle_id"), sa.column("id"), sa.column("outcome"), sa.column("finished_at"),
        sa.column("diagnostics", sa.JSON()),
    )
    conn = op.get_bind()
    rows = conn.execute(
        sa.select(ident.c.id, ident.c.outcome, ident.c.finished_at, ident.c.diagnostics)
        .where(ident.c.spindle_id == sid, ident.c.diagnostics.is_not(None))
        .order_by(ident.c.id)
    ).all()
    newest = None
    for rid, outcome, finished_at, diag in rows:
        if isinstance(diag, str):
            diag = json.loads(diag)
        stored = diag.get("speed_map") if isinstance(diag, dict) else None
        if not isinstance(stored, dict) or not any(k in stored for k in COV_KEYS):
            continue
        if outcome == "ok":
            newest = (rid, finished_at, stored)
        light = {k: v for k, v in stored.items() if k not in COV_KEYS}
        light["covariance_in"] = "speed_map_state"
        conn.execute(
            ident.update()
            .where(ident.c.spindle_id == sid, ident.c.id == rid)
            .values(diagnostics={**diag, "speed_map": light})
        )
    if newest is not None:
        state = sa.table(
            "speed_map_state", sa.column("spindle_id"), sa.column("identification_id"),
            sa.column("fitted_at", sa.DateTime(True)), sa.column("state", sa.JSON()),
        )
        rid, finished_at, stored = newest
        if isinstance(finished_at, str):
            finished_at = datetime.fromisoformat(finished_at)
        if finished_at.tzinfo is None:
            finished_at = finished_at.replace(tzinfo=UTC)
        conn.execute(state.insert().values(spindle_id=sid, identification_id=rid, fitted_at=finished_at,
                                           state=stored))


def downgrade() -> None:
    sid = _spindle_id()
    op.drop_table("speed_map_state")
    op.drop_table("samples_1min")
    for name, pk, _indexes in TABLES:
        _downgrade_table(name, pk, sid)
    for name, *_ in reversed(TABLES):
        op.drop_table(f"{name}_old")
    op.drop_table("spindles")


def _downgrade_table(name: str, pk: tuple[str, ...], sid: str) -> None:
    serial = pk == ("id",) or name == "samples"
    old = _retire(
        name,
        had_id_seq=serial and name != "samples",
        pk_old=f"pk_{name}",
        fk_old=[f"fk_{name}_spindle_id_spindles"] + ([COND_FK] if name == "identifications" else []),
    )
    cols = []
    for c in old.columns:
        if c.name == "spindle_id":
            continue
        typ = sa.Integer() if c.name == "id" and serial else c.type
        if isinstance(c.type, sa.DateTime):
            typ = sa.DateTime(timezone=True)
        elif isinstance(c.type, sa.JSON | postgresql.ARRAY):
            typ = sa.JSON()
        cols.append(sa.Column(c.name, typ, nullable=c.nullable))
    names = [c.name for c in cols]
    if name == "samples":
        cols.insert(0, sa.Column("id", sa.Integer(), nullable=False))
    extra: list[SchemaItem] = []
    if name == "identifications":
        extra.append(sa.ForeignKeyConstraint(["condition_id"], ["conditions.id"],
                                             name="fk_identifications_condition_id_conditions",
                                             ondelete="CASCADE"))
    op.create_table(name, *cols, sa.PrimaryKeyConstraint("id", name=f"pk_{name}"), *extra)
    for ix in OLD_INDEXES[name]:
        op.create_index(_ix(name, ix), name, list(ix), unique=False)
    exprs = [f'"{n}"' for n in names]
    if name == "samples" and _pg():
        exprs[names.index("temps_c")] = "array_to_json(temps_c)"
    where = f"WHERE spindle_id = '{sid}'" + (" ORDER BY t" if name == "samples" else "")
    _copy(name, names, exprs, where=where, ignore=False)
    if serial:
        _reset_sequence(name)
