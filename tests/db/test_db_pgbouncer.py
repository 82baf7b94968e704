"""The store behind a real PgBouncer in transaction mode (issue 29 item 4).

PgBouncer (Debian's ``pgbouncer``) runs on a free loopback port in front of this machine's PostgreSQL with
``pool_mode = transaction`` and two server connections, so consecutive transactions of one client land on
different server connections. Each test has its own database (PgBouncer refuses the ``options`` startup
parameter the other database tests use for a schema). Checked, each beside a control that shows the failure
it guards against happens in this set-up:

- with ``transaction_pooling`` (psycopg's prepared statements off) a statement run often enough to be
  prepared still works when the next transaction lands on another server connection; without it, it fails;
- the statement timeout is ``SET LOCAL``: it cancels a slow statement of ours, and another client of the same
  server connections sees the server's default afterwards; a per-connection ``SET`` leaks to that client.
"""

from __future__ import annotations

import os
import pwd
import shutil
import socket
import subprocess
import tempfile
import time
import uuid
from collections.abc import Iterator
from pathlib import Path

import psycopg
import pytest
import sqlalchemy as sa
from sqlalchemy.engine import make_url

from service.store import migrate
from service.store.engine import create_db_engine
from service.store.errors import DatabaseError

pytestmark = pytest.mark.postgres

PGBOUNCER = shutil.which("pgbouncer") or "/usr/sbin/pgbouncer"
PREPARE_AFTER = 5  # psycopg's default prepare_threshold: a query is prepared on its 6th execution


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _wait_port(port: int, proc: subprocess.Popen[bytes], log: Path, timeout_s: float = 10.0) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            pytest.fail(f"pgbouncer exited ({proc.returncode}): {log.read_text(errors='replace')[-2000:]}")
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=0.2):
                return
        except OSError:
            time.sleep(0.05)
    pytest.fail(f"pgbouncer did not listen on 127.0.0.1:{port} within {timeout_s} s")


@pytest.fixture
def bouncer(pg_url: str) -> Iterator[str]:
    """A fresh database behind a transaction-mode PgBouncer; yields the SQLAlchemy URL through it."""
    if not os.path.exists(PGBOUNCER):
        if os.environ.get("CI"):
            pytest.fail("pgbouncer not installed (required in CI: .ci/run installs it)")
        pytest.skip("pgbouncer not installed")
    target = make_url(pg_url)
    name = f"chtc_pgb_{uuid.uuid4().hex[:10]}"
    admin = sa.create_engine(pg_url, isolation_level="AUTOCOMMIT")
    with admin.connect() as conn:
        conn.exec_driver_sql(f'CREATE DATABASE "{name}"')
    # PgBouncer will not run as root: it drops to the postgres user, who must read its files
    work = Path(tempfile.mkdtemp(prefix="chtc-pgbouncer-"))
    port = _free_port()
    user = target.username or "postgres"
    (work / "users.txt").write_text(f'"{user}" ""\n')
    (work / "pgbouncer.ini").write_text(
        f"[databases]\n{name} = host={target.host or '127.0.0.1'} port={target.port or 5432} dbname={name}\n"
        "[pgbouncer]\nlisten_addr = 127.0.0.1\n"
        f"listen_port = {port}\nauth_type = trust\nauth_file = {work / 'users.txt'}\n"
        "pool_mode = transaction\ndefault_pool_size = 2\nmin_pool_size = 0\nserver_round_robin = 0\n"
        f"unix_socket_dir =\nlogfile = {work / 'pgbouncer.log'}\n"
    )
    cmd = [PGBOUNCER, str(work / "pgbouncer.ini")]
    if os.geteuid() == 0:
        pw = pwd.getpwnam("postgres")
        work.chmod(0o755)
        for p in [work, *work.iterdir()]:
            os.chown(p, pw.pw_uid, pw.pw_gid)
        cmd[1:1] = ["-u", "postgres"]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT)
    try:
        _wait_port(port, proc, work / "pgbouncer.log")
        yield target.set(port=port, database=name).render_as_string(hide_password=False)
    finally:
        proc.terminate()
        proc.wait(10)
        with admin.connect() as conn:
            conn.exec_driver_sql(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)')
        admin.dispose()
        shutil.rmtree(work, ignore_errors=True)


def _raw(url: str) -> psycopg.Connection[tuple[object, ...]]:
    """A plain psycopg client of the same pooler (autocommit: each statement its own transaction)."""
    return psycopg.connect(**_raw_kwargs(url), autocommit=True, prepare_threshold=None)


def _show_timeout(conn: psycopg.Connection[tuple[object, ...]]) -> str:
    row = conn.execute("SHOW statement_timeout").fetchone()
    assert row is not None
    return str(row[0])


def _hold_last_server(url: str) -> psycopg.Connection[tuple[object, ...]]:
    """Another client that opens a transaction and keeps it: it takes the server connection used last
    (PgBouncer reuses the most recent idle one), so our next transaction lands on the other one."""
    holder = psycopg.connect(**_raw_kwargs(url), autocommit=False, prepare_threshold=None)
    holder.execute("SELECT 1")
    return holder


def _raw_kwargs(url: str) -> dict[str, object]:
    u = make_url(url)
    return {"host": u.host, "port": u.port, "dbname": u.database, "user": u.username}


def _run_prepared_then_switch(engine: sa.Engine, url: str) -> None:
    """Run one parametrised query past psycopg's prepare threshold on one pooled connection, then once more
    while another client holds the server connection it was prepared on."""
    query = sa.text("SELECT count(*) FROM alembic_version WHERE version_num <> :v")
    with engine.connect() as conn:  # one client connection throughout
        for i in range(PREPARE_AFTER + 2):
            with conn.begin():
                conn.execute(query, {"v": f"x{i}"}).scalar_one()
        holder = _hold_last_server(url)
        try:
            with conn.begin():
                conn.execute(query, {"v": "after"}).scalar_one()
        finally:
            holder.close()


def test_transaction_pooling_runs_prepared_queries_across_server_connections(bouncer: str) -> None:
    engine = create_db_engine(bouncer, statement_timeout_s=5.0, transaction_pooling=True)
    try:
        migrate.upgrade(engine)  # the schema, through the pooler
        _run_prepared_then_switch(engine, bouncer)
    finally:
        engine.dispose()


def test_control_prepared_statements_fail_behind_transaction_pooling(bouncer: str) -> None:
    """The control: psycopg's default (prepared after 5 runs) breaks once the server connection changes.
    (``create_db_engine`` without ``transaction_pooling`` cannot even connect through PgBouncer: it sends the
    session limits as the ``options`` startup parameter, which PgBouncer refuses; a plain engine shows the
    prepared statements' failure alone.)"""
    with pytest.raises(DatabaseError, match="options"):
        migrate.upgrade(create_db_engine(bouncer, statement_timeout_s=5.0, transaction_pooling=False))
    engine = sa.create_engine(bouncer, pool_pre_ping=True)
    try:
        migrate.upgrade(engine)
        with pytest.raises(sa.exc.DBAPIError, match="prepared statement"):
            _run_prepared_then_switch(engine, bouncer)
    finally:
        engine.dispose()


def test_statement_timeout_cancels_ours_and_does_not_leak(bouncer: str) -> None:
    engine = create_db_engine(bouncer, statement_timeout_s=0.5, transaction_pooling=True)
    try:
        with engine.connect() as conn:
            with conn.begin():
                assert conn.exec_driver_sql("SHOW statement_timeout").scalar_one() == "500ms"
            with pytest.raises(sa.exc.OperationalError, match="statement timeout"), conn.begin():
                conn.exec_driver_sql("SELECT pg_sleep(2)")
            with conn.begin():  # the connection is usable after the cancel
                assert conn.exec_driver_sql("SELECT 1").scalar_one() == 1
        # every server connection our transactions used now serves another client with the default
        with _raw(bouncer) as other, _raw(bouncer) as another:
            seen = {_show_timeout(c) for c in (other, another) for _ in range(3)}
        assert seen == {"0"}
    finally:
        engine.dispose()


def test_control_a_per_connection_set_leaks_to_the_next_client(bouncer: str) -> None:
    """The control: what ``SET statement_timeout`` per connection (the store before) does behind the
    pooler: the next client of that server connection inherits it."""
    with _raw(bouncer) as ours:
        ours.execute("SET statement_timeout = 1234")
    with _raw(bouncer) as other:
        assert _show_timeout(other) == "1234ms"
