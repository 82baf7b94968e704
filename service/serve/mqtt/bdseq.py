"""The Sparkplug birth/death sequence number ``bdSeq`` kept in a small file, so that it survives restarts.

Every CONNECT carries the next number (0–255, wrapping) in its Will (NDEATH), and the NBIRTH after it the
same, so a host matches a death to its birth. The number is stored once the broker accepted the CONNECT
(``commit``): a try refused before (broker down) uses no number, so the numbers of accepted sessions are
consecutive. After a ``kill -9`` the broker sends the last Will; the next start continues with
the number after it, so the host never takes an old death for the new session.
"""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["BdSeqStore"]


class BdSeqStore:
    """``upcoming()``: the number for the next CONNECT; ``commit(n)`` once it is accepted (atomic write)."""

    def __init__(self, path: Path) -> None:
        self.path = Path(path)

    def last(self) -> int | None:
        """The number stored by the last connect (None: none yet, or an unreadable file)."""
        try:
            value = int(self.path.read_text(encoding="ascii").strip())
        except (OSError, ValueError):
            return None
        return value if 0 <= value <= 255 else None

    def upcoming(self) -> int:
        last = self.last()
        return 0 if last is None else (last + 1) % 256

    def commit(self, value: int) -> None:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        tmp = self.path.with_name(self.path.name + ".tmp")
        tmp.write_text(f"{value}\n", encoding="ascii")
        os.replace(tmp, self.path)
