"""The newest time a database holds: where a simulated clock must start so that it never runs behind it.

``chtc demo`` runs plant time faster than the wall clock; re-run on its own database, a clock started at the
wall clock again would date the new samples before the stored ones (issue 41: a live state, conditions and
identifications "from the future"). The demo starts its clock after ``newest_time``.
"""

from __future__ import annotations

from datetime import datetime

from sqlalchemy import inspect, select
from sqlalchemy.engine import Engine
from sqlalchemy.sql import func

from service.store.models import Condition, DeviceEvent, Identification, LiveStateRow, SampleRow

__all__ = ["newest_sample_time", "newest_time"]

_COLUMNS: tuple[tuple[type, str], ...] = (
    (SampleRow, "t"),
    (Condition, "started_at"),
    (Identification, "window_end"),
    (Identification, "finished_at"),
    (LiveStateRow, "at"),
    (DeviceEvent, "t"),
)


def newest_time(engine: Engine) -> datetime | None:
    """The latest UTC time stored in any spindle's samples, conditions, identifications, live state or device
    events (None: an empty or not yet migrated database)."""
    tables = set(inspect(engine).get_table_names())
    newest: datetime | None = None
    with engine.connect() as conn:
        for model, name in _COLUMNS:
            if getattr(model, "__tablename__", None) not in tables:
                continue
            value = conn.scalar(select(func.max(getattr(model, name))))
            if isinstance(value, datetime) and (newest is None or value > newest):
                newest = value
    return newest


def newest_sample_time(engine: Engine) -> datetime | None:
    """The newest stored sample's UTC time, any spindle (None: none stored): a replay's "now" for the
    retention pass."""
    with engine.connect() as conn:
        value = conn.scalar(select(func.max(SampleRow.t)))
    return value if isinstance(value, datetime) else None
