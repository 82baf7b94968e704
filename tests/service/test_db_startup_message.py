"""``chtc run`` without ``--migrate`` on a new database: the message says the schema is missing, not that the
database is unreachable (it is reachable)."""

from __future__ import annotations

from service.persistence import open_persistence
from service.settings import Settings


def test_new_database_without_migrate_names_the_missing_schema(tmp_path) -> None:
    db = Settings().database.model_copy(update={"url": f"sqlite:///{tmp_path / 'new.db'}"})
    said: list[str] = []
    p = open_persistence(db, migrate=False, on_event=said.append)
    try:
        status = p.sink.status()
        assert not status.connected
        assert "no chtc schema" in status.last_error and "--migrate" in status.last_error
        assert "not reachable" not in status.last_error
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
