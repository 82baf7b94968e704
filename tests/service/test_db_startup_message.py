"""``chtc run`` without ``--migrate`` on a new database: the message says the schema is missing, not that the
database is unreachable (it is reachable)."""

from __future__ import annotations

from service.host.persistence import open_persistence
from service.settings import Settings


def test_new_database_without_migrate_names_the_missing_schema(tmp_path, caplog) -> None:
    import logging

    db = Settings().database.model_copy(update={"url": f"sqlite:///{tmp_path / 'new.db'}"})
    with caplog.at_level(logging.WARNING, logger="service.host.persistence"):
        p = open_persistence(db, migrate=False)
    try:
        status = p.sink.status()
        assert not status.connected
        assert "no chtc schema" in status.last_error and "--migrate" in status.last_error
        assert "not reachable" not in status.last_error
        said = [r.getMessage() for r in caplog.records]  # a warning: shown also by chtc demo --quiet
        assert len(said) == 1 and "no chtc schema" in said[0]
    finally:
        p.close()


def test_unreachable_database_says_so() -> None:
    url = "postgresql+psycopg://postgres@127.0.0.1:1/test"  # nothing listens on port 1: refused at once
    db = Settings().database.model_copy(update={"url": url})
    p = open_persistence(db, migrate=False)
    try:
        assert p.sink.status().last_error.startswith("database not reachable")
    finally:
        p.close()


def test_retries_log_a_problem_once(tmp_path, caplog) -> None:
    """The background retry (every 2 s) used to log "database not ready" on every attempt."""
    import asyncio
    import logging

    db = Settings().database.model_copy(update={"url": f"sqlite:///{tmp_path / 'new.db'}"})
    p = open_persistence(db, migrate=False)

    async def retry_a_few_times() -> None:
        task = asyncio.ensure_future(p.ensure_open(retry_s=0.01))
        deadline = asyncio.get_running_loop().time() + 0.5  # dozens of retries at 10 ms
        while asyncio.get_running_loop().time() < deadline:
            await asyncio.sleep(0.05)
        task.cancel()

    try:
        with caplog.at_level(logging.INFO, logger="service.host.persistence"):
            asyncio.run(retry_a_few_times())
        assert [r for r in caplog.records if "not ready" in r.getMessage()] == []
    finally:
        p.close()
