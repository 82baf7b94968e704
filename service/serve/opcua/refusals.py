"""The OPC UA server's refusals: counted (``/metrics``, ``chtc_outlet_refused_total``) and logged at INFO
once per client and reason, not at ERROR per request.

asyncua logs every refused request at ERROR (``asyncua.server.uaprocessor``: "sending service fault
response") and a WARNING besides for a request the permission rules refuse: an anonymous client that keeps
writing fills the log. :class:`Refusals` is told of each refusal (``note``) by the rules
(``service.serve.opcua.security.ReadOnlyRules``: the request and the session's user) and by
:class:`FaultFilter`, which takes asyncua's records of service faults off its logger (the faults the rules
already noted are dropped; any other, e.g. ``BadTooManySessions``, is noted with its status name).

The client is the session's identity (``anonymous`` or the user's name): the server has no other name for
it where it decides.
"""

from __future__ import annotations

import logging
import threading
from collections import Counter

__all__ = ["FaultFilter", "Refusals", "install_fault_filter"]

log = logging.getLogger(__name__)
UAPROCESSOR = "asyncua.server.uaprocessor"
_FAULT = "sending service fault response: %s (%s)"
_DENIED = "%s attempted to do something they are not permitted to do"


class Refusals:
    """Refusals by reason (thread-safe: asyncua's loop notes, ``/metrics`` reads from another thread)."""

    def __init__(self, logger: logging.Logger = log) -> None:
        self._counts: Counter[str] = Counter()
        self._logged: set[tuple[str, str]] = set()
        self._lock = threading.Lock()
        self._log = logger

    def note(self, client: str, reason: str) -> None:
        with self._lock:
            self._counts[reason] += 1
            first = (client, reason) not in self._logged
            self._logged.add((client, reason))
        if first:
            self._log.info(
                "OPC UA: refused %s for %s (logged once per client and reason; all counted in "
                "/metrics chtc_outlet_refused_total)",
                reason,
                client,
            )

    def counts(self) -> dict[str, int]:
        with self._lock:
            return dict(self._counts)


class FaultFilter(logging.Filter):
    """On asyncua's ``uaprocessor`` logger: drops its ERROR per service fault and its WARNING per refused
    request; a fault other than BadUserAccessDenied (which the rules noted) goes to ``refusals``. Only the
    records of ``thread`` (the server's own: each server runs its loop in a thread of its own), so two
    servers in one process count their own refusals."""

    def __init__(self, refusals: Refusals, thread: int) -> None:
        super().__init__()
        self.refusals = refusals
        self.thread = thread

    def filter(self, record: logging.LogRecord) -> bool:
        if record.thread != self.thread:
            return True
        if record.msg == _DENIED:
            return False
        if record.msg == _FAULT:
            args = record.args if isinstance(record.args, tuple) else ()
            name = str(args[1]) if len(args) > 1 else "fault"
            if name != "BadUserAccessDenied":
                self.refusals.note("a client", name)
            return False
        return True


def install_fault_filter(refusals: Refusals) -> FaultFilter:
    """Add a :class:`FaultFilter` for ``refusals`` and the calling thread (the server's) to asyncua's logger;
    remove it with ``logging.getLogger(UAPROCESSOR).removeFilter(f)``."""
    f = FaultFilter(refusals, threading.get_ident())
    logging.getLogger(UAPROCESSOR).addFilter(f)
    return f
