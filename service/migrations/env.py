"""Alembic environment: programmatic use passes a connection in ``config.attributes["connection"]``;
CLI use takes the URL from ``sqlalchemy.url`` or ``CHTC_DATABASE__URL``. Logging is left to the caller."""

from __future__ import annotations

import os
import re

from alembic import context
from sqlalchemy.engine import Connection

from service.store.engine import create_db_engine
from service.store.models import Base

config = context.config
target_metadata = Base.metadata


def _url() -> str:
    url = config.get_main_option("sqlalchemy.url") or os.environ.get("CHTC_DATABASE__URL")
    if not url:
        raise RuntimeError("no database URL: set sqlalchemy.url or CHTC_DATABASE__URL")
    return url


PARTITION = re.compile(r"^samples_p\d{8}$")  # service.store.partitions: made and dropped at run time


def include_object(obj: object, name: str | None, type_: str, reflected: bool, compare_to: object) -> bool:
    """Autogenerate ignores the daily partitions of ``samples`` (it would propose dropping them)."""
    return not (type_ == "table" and reflected and name is not None and PARTITION.match(name))


def _configure(connection: Connection) -> None:
    context.configure(
        connection=connection,
        target_metadata=target_metadata,
        include_object=include_object,
        compare_type=True,
        render_as_batch=connection.dialect.name == "sqlite",
        on_version_apply=config.attributes.get("on_version_apply", ()),  # progress (service.store.migrate)
    )
    with context.begin_transaction():
        context.run_migrations()


def run_offline() -> None:
    context.configure(url=_url(), target_metadata=target_metadata, literal_binds=True)
    with context.begin_transaction():
        context.run_migrations()


def run_online() -> None:
    connection = config.attributes.get("connection")
    if connection is not None:
        _configure(connection)
        return
    engine = create_db_engine(_url())
    try:
        with engine.begin() as conn:
            _configure(conn)
    finally:
        engine.dispose()


if context.is_offline_mode():
    run_offline()
else:
    run_online()
