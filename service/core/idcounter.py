"""Condition and identification ids: a counter that knows whether it issued one, and the re-base to the
database's ids when the database answers only after start-up.

With the database unreachable at start-up the service cannot know the stored ids, so new ids start from a
time-based base that no stored row can have (``service.host.persistence.fallback_restored``): numbers like
1795761900000. When the database answers before the first id was needed (the usual case: a database that
starts after the service), ``rebase_ids`` makes the ids continue from the stored ones instead: small and
monotonic across runs. Once an id was issued, it and everything after it keep the time base for this run
(renumbering records the API has served is not done). Pure: no I/O.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

__all__ = ["IdCounter", "IdsKnown", "rebase_ids"]


class IdCounter:
    """``next(counter)`` gives ``start``, ``start + 1``, ...; ``issued`` says whether it gave any yet."""

    def __init__(self, start: int) -> None:
        self._next = int(start)
        self.issued = False

    def __iter__(self) -> IdCounter:
        return self

    def __next__(self) -> int:
        value, self._next = self._next, self._next + 1
        self.issued = True
        return value

    @property
    def next_id(self) -> int:
        """The id ``next()`` gives next."""
        return self._next

    def rebase(self, start: int) -> None:
        """Continue from ``start`` (only before the first id: an issued id is never given twice)."""
        if self.issued:
            raise ValueError(f"ids were issued from {self._next}; cannot re-base to {start}")
        self._next = int(start)


@dataclass(frozen=True)
class IdsKnown:
    """Event: the database answered after start-up; its next free ids (largest stored + 1)."""

    event_id: str
    next_condition_id: int
    next_identification_id: int


def rebase_ids(
    event: IdsKnown, conditions: IdCounter, identifications: IdCounter, log: Callable[[str], None]
) -> None:
    """Both counters continue from the database's ids if neither issued one yet; ``log`` says which."""
    if conditions.issued or identifications.issued:
        log(
            f"db: answered after ids were issued; this run keeps them (conditions from "
            f"{conditions.next_id}, identifications from {identifications.next_id})"
        )
        return
    conditions.rebase(event.next_condition_id)
    identifications.rebase(event.next_identification_id)
    log(
        f"db: answered; ids continue from the stored ones (condition {event.next_condition_id}, "
        f"identification {event.next_identification_id})"
    )
