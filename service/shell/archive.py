"""The identification history the API pages through: the database (bounded reads with a deadline) merged with
the records this process made and the writer may still hold; the records in memory when the database is down.

Readers run on API threads; ``records`` comes from the core's published view (``CoreView.records``).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from datetime import datetime
from typing import TYPE_CHECKING, TypeVar

from service.contracts.errors import NotFoundError, NotReadyError
from service.contracts.snapshots import IdentificationPage, IdentificationRecord
from service.serve.views import row_to_record

if TYPE_CHECKING:
    from sqlalchemy.orm import Session, sessionmaker

    from service.store.reads import DbReads

__all__ = ["IdentificationArchive"]

log = logging.getLogger(__name__)
T = TypeVar("T")


class IdentificationArchive:
    """See the module docstring; without a ``session_factory`` only the records in memory exist."""

    def __init__(self, session_factory: sessionmaker[Session] | None, db_reads: DbReads | None) -> None:
        self.session_factory = session_factory
        self.db_reads = db_reads

    def page(
        self,
        records: Sequence[IdentificationRecord],
        *,
        since: datetime | None,
        until: datetime | None,
        limit: int,
        offset: int,
    ) -> IdentificationPage:
        partial = None
        if self.session_factory is not None:
            try:
                return self._db_page(records, since=since, until=until, limit=limit, offset=offset)
            except NotReadyError:  # the database is hung (read timed out or every read slot taken): 503
                raise
            except Exception as err:  # database down: serve what this process remembers, marked partial
                log.warning("identification history from memory (database: %s)", err)
                partial = f"database not readable, only the records in memory: {err}"
        rows = [r for r in records if _within(r, since, until)]
        rows.sort(key=lambda r: (r.finished_at, r.id), reverse=True)
        return IdentificationPage(
            items=rows[offset : offset + limit],
            total=len(rows),
            limit=limit,
            offset=offset,
            partial_reason=partial,
        )

    def get(self, records: Sequence[IdentificationRecord], identification_id: int) -> IdentificationRecord:
        for r in records:
            if r.id == identification_id:
                return r
        if self.session_factory is not None:
            from service.store.errors import DatabaseError, RecordNotFoundError
            from service.store.repository import get_identification

            try:
                return self._db_read(
                    lambda session: row_to_record(get_identification(session, identification_id)),
                    "get identification",
                )
            except RecordNotFoundError:
                pass
            except DatabaseError as err:  # down or refusing: a 503 naming the reason, not a 500
                raise NotReadyError(f"identification {identification_id}: {err}") from err
        raise NotFoundError(f"identification {identification_id} not found")

    def _db_page(
        self,
        records: Sequence[IdentificationRecord],
        *,
        since: datetime | None,
        until: datetime | None,
        limit: int,
        offset: int,
    ) -> IdentificationPage:
        from service.store.repository import list_identifications

        def read(session: Session) -> IdentificationPage:
            page = list_identifications(session, since=since, until=until, limit=limit, offset=offset)
            return IdentificationPage(
                items=[row_to_record(r) for r in page.items], total=page.total, limit=limit, offset=offset
            )

        return _merge_pending(self._db_read(read, "list identifications"), records, since, until)

    def _db_read(self, fn: Callable[[Session], T], what: str) -> T:
        """``fn(session)`` through the bounded read pool, else inline. A hung database (every read slot taken,
        or no answer in time: the store's ``DatabaseBusyError`` / ``DatabaseTimeoutError``) is the API's
        ``NotReadyError`` (503): translated here, once; the store raises no API error."""
        if self.db_reads is not None:
            from service.store.errors import DatabaseBusyError, DatabaseTimeoutError

            try:
                return self.db_reads.run(fn, what)
            except (DatabaseBusyError, DatabaseTimeoutError) as err:
                raise NotReadyError(str(err)) from err
        from service.store.repository import session_scope

        assert self.session_factory is not None
        with session_scope(self.session_factory, what) as session:
            return fn(session)


def _merge_pending(
    page: IdentificationPage,
    records: Sequence[IdentificationRecord],
    since: datetime | None,
    until: datetime | None,
) -> IdentificationPage:
    """Records still in the writer's buffer are not in the database yet: show them on the first page."""
    if page.offset != 0:
        return page
    stored = {r.id for r in page.items}
    newest_stored = max((r.id for r in page.items), default=0)
    extra = [r for r in records if r.id not in stored and r.id > newest_stored and _within(r, since, until)]
    if not extra:
        return page
    items = sorted([*extra, *page.items], key=lambda r: (r.finished_at, r.id), reverse=True)
    return IdentificationPage(
        items=items[: page.limit], total=page.total + len(extra), limit=page.limit, offset=page.offset
    )


def _within(r: IdentificationRecord, since: datetime | None, until: datetime | None) -> bool:
    return (since is None or r.finished_at >= since) and (until is None or r.finished_at < until)
