"""The outlet's bounded outgoing buffer and its counters (never blocks the producer).

The producer (``put``) never waits: when the buffer is full the oldest message is dropped and counted. The
publisher takes messages in order and puts one back at the front if the send failed. Not thread-safe: the
outlet uses it on the event loop only.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from typing import Generic, TypeVar

__all__ = ["OutBuffer", "OutletCounters"]

T = TypeVar("T")


@dataclass
class OutletCounters:
    """Counted since start: messages sent, dropped (buffer full), connects after the first
    (``reconnects``), failed connect attempts, births sent (connects and rebirths), rebirth requests
    received and honoured; ``connected`` now."""

    sent: int = 0
    dropped: int = 0
    reconnects: int = 0
    connect_failures: int = 0
    births: int = 0
    rebirth_requests: int = 0
    rebirths: int = 0
    connected: bool = False


class OutBuffer(Generic[T]):
    def __init__(self, maxlen: int) -> None:
        if maxlen < 1:
            raise ValueError(f"maxlen: must be >= 1, got {maxlen}")
        self.maxlen = int(maxlen)
        self._items: deque[T] = deque()
        self.dropped = 0

    def __len__(self) -> int:
        return len(self._items)

    def put(self, item: T) -> None:
        if len(self._items) >= self.maxlen:
            self._items.popleft()
            self.dropped += 1
        self._items.append(item)

    def put_back(self, item: T) -> None:
        """A message whose send failed goes back to the front (it is the oldest)."""
        if len(self._items) >= self.maxlen:
            self.dropped += 1
            return
        self._items.appendleft(item)

    def peek(self) -> T | None:
        """The oldest message, left in place (None: empty)."""
        return self._items[0] if self._items else None

    def take(self) -> T | None:
        """The oldest message (None: empty)."""
        return self._items.popleft() if self._items else None
