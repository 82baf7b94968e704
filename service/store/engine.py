"""Engine and session factory, built at the edge from ``settings.database`` (nothing opens at import).

SQLite gets WAL journaling (readers never block the writer thread), ``foreign_keys=ON`` and a busy timeout on
every new connection; its parent directory is created. PostgreSQL gets a connect timeout, pre-ping (a
restarted server is noticed on the next checkout instead of failing a write), a server-side
``statement_timeout`` (a slow statement is cancelled), TCP keepalives and ``tcp_user_timeout`` (a dead peer
is noticed by the kernel).

Behind a pooler in transaction mode (PgBouncer ``pool_mode = transaction``) a server connection serves many
clients, one transaction at a time, so nothing may outlive a transaction: the statement timeout is set with
``SET LOCAL`` at the start of every transaction (never per connection, which would leak to the next client of
that server connection), and ``transaction_pooling`` turns psycopg's prepared statements off
(``prepare_threshold=None``: a statement prepared on one server connection is unknown, or already known, on
the next one; measured 6 of 240 transactions failing with ``DuplicatePreparedStatement``). The ``options``
startup parameter (``-csearch_path=…``) is refused by PgBouncer: use a database per schema there.
None of these sees a link that freezes without a reset; ``service.store.watchdog`` covers that on the client.
The server side of such a freeze (the backend the lost connection leaves, holding its transaction's locks) is
bounded by ``service.store.sessions``: per-session keepalives, ``tcp_user_timeout`` and
``idle_in_transaction_session_timeout`` sent as startup options, and the orphaned backend ended from the next
connection (not behind a transaction-mode pooler, see there).
"""

from __future__ import annotations

from pathlib import Path

from sqlalchemy import Connection, Engine, create_engine, event
from sqlalchemy.engine import make_url
from sqlalchemy.engine.interfaces import DBAPIConnection
from sqlalchemy.orm import ORMExecuteState, Session, sessionmaker, with_loader_criteria
from sqlalchemy.pool import ConnectionPoolEntry

from service.store.dburl import normalize_database_url
from service.store.errors import DatabaseUnavailableError
from service.store.sessions import end_orphans, server_options

# What the store is built and tested for: backend -> the SQLAlchemy drivers (a URL's ``+driver``).
SUPPORTED_DATABASES: dict[str, tuple[str, ...]] = {"sqlite": ("pysqlite",), "postgresql": ("psycopg",)}


def create_db_engine(
    url: str,
    *,
    echo: bool = False,
    connect_timeout_s: float = 5.0,
    statement_timeout_s: float | None = None,
    sqlite_busy_timeout_ms: int = 5000,
    create_dirs: bool = True,
    pool_size: int | None = None,
    max_overflow: int = 0,
    transaction_pooling: bool = False,
    pre_ping: bool = True,
) -> Engine:
    """An engine for ``url`` (``sqlite:///path`` or ``postgresql+psycopg://…``), configured as above.

    ``statement_timeout_s`` (PostgreSQL) is set with ``SET LOCAL`` in every transaction, so a ``options``
    query parameter in the URL (a ``search_path``) is kept and nothing leaks through a pooler;
    ``pool_size`` and ``max_overflow`` bound the pool (None: SQLAlchemy's defaults, 5 and 10);
    ``transaction_pooling``: the server is reached through a transaction-mode pooler (no prepared statements);
    ``pre_ping``: test each pooled connection (``SELECT 1``) before it is handed out (PostgreSQL).
    """
    url = normalize_database_url(url)  # postgres://, postgresql:// -> postgresql+psycopg://
    parsed = make_url(url)
    if parsed.get_backend_name() == "sqlite":
        return _sqlite_engine(url, echo=echo, busy_timeout_ms=sqlite_busy_timeout_ms, create_dirs=create_dirs)
    kwargs: dict[str, object] = {}
    if pool_size is not None:
        kwargs = {"pool_size": pool_size, "max_overflow": max_overflow}
    if parsed.get_backend_name() != "postgresql":
        return create_engine(url, echo=echo, pool_pre_ping=pre_ping, **kwargs)
    timeout = max(1, round(connect_timeout_s))
    user_timeout_ms = 1000 * max(timeout, 10)
    connect_args: dict[str, object] = {
        "connect_timeout": timeout,
        "keepalives": 1,
        "keepalives_idle": 10,
        "keepalives_interval": 5,
        "keepalives_count": 3,
        "tcp_user_timeout": user_timeout_ms,
    }
    if transaction_pooling:
        connect_args["prepare_threshold"] = None
    else:  # PgBouncer refuses the options startup parameter (and its server sessions are its own)
        base = parsed.query.get("options", "")
        base = " ".join(base) if isinstance(base, tuple) else base
        connect_args["options"] = server_options(user_timeout_ms=user_timeout_ms, base=base)
    engine = create_engine(url, echo=echo, pool_pre_ping=pre_ping, connect_args=connect_args, **kwargs)
    if not transaction_pooling:
        end_orphans(engine)
    if statement_timeout_s is not None:
        ms = max(1, round(1000 * statement_timeout_s))

        @event.listens_for(engine, "begin")
        def _on_begin(conn: Connection) -> None:
            # one extra statement per transaction (~0.1 ms on loopback); it ends with the transaction
            conn.exec_driver_sql(f"SET LOCAL statement_timeout = {ms}")

    return engine


def _sqlite_engine(url: str, *, echo: bool, busy_timeout_ms: int, create_dirs: bool) -> Engine:
    database = make_url(url).database
    in_memory = database in (None, "", ":memory:") or str(database).startswith("file::memory:")
    if create_dirs and not in_memory:
        parent = Path(str(database)).expanduser().parent
        try:
            parent.mkdir(parents=True, exist_ok=True)
        except OSError as err:
            raise DatabaseUnavailableError(f"cannot create the SQLite directory {parent}: {err}") from err
    engine = create_engine(url, echo=echo, connect_args={"timeout": busy_timeout_ms / 1000.0})

    @event.listens_for(engine, "connect")
    def _on_connect(dbapi_conn: DBAPIConnection, _record: ConnectionPoolEntry) -> None:
        cursor = dbapi_conn.cursor()
        try:
            if not in_memory:
                cursor.execute("PRAGMA journal_mode=WAL")
            cursor.execute("PRAGMA foreign_keys=ON")
            cursor.execute(f"PRAGMA busy_timeout={int(busy_timeout_ms)}")
        finally:
            cursor.close()

    return engine


DEFAULT_SPINDLE_ID = "spindle1"  # the settings' default ([spindle] id) and the id 0007 gives old rows


def make_session_factory(engine: Engine, *, spindle_id: str = DEFAULT_SPINDLE_ID) -> sessionmaker[Session]:
    """Sessions of one spindle that keep loaded attributes after commit (rows are handed to other threads
    read-only).

    Every ORM query, update and delete run in these sessions sees only ``spindle_id``'s rows: a
    ``with_loader_criteria`` on every spindle-scoped table (``service.store.models.SpindleScoped``) is added
    to each statement, in subqueries and joins too, so no query can forget the filter. Writes stamp the id
    (``service.store.repository.write_records``); ``session.info["spindle_id"]`` holds it.
    """
    factory = sessionmaker(engine, expire_on_commit=False, info={"spindle_id": spindle_id})
    event.listen(factory, "do_orm_execute", _only_this_spindle)
    return factory


def _only_this_spindle(state: ORMExecuteState) -> None:
    from service.store.models import SpindleScoped

    if not (state.is_select or state.is_update or state.is_delete) or state.is_column_load:
        return
    sid = state.session.info["spindle_id"]
    state.statement = state.statement.options(
        with_loader_criteria(SpindleScoped, lambda cls: cls.spindle_id == sid, include_aliases=True)
    )
