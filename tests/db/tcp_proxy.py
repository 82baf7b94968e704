"""A tiny TCP forwarder on 127.0.0.1 used to make a real PostgreSQL appear, disappear or hang on a port.

``stop()`` is a server going away (connections reset); ``freeze()`` is a hung server or a frozen link: the
proxy keeps every connection open and keeps accepting, but forwards nothing (data read meanwhile is held, in
order) until ``thaw()``. No RST, no FIN: only a client-side timeout can notice it.

What a frozen link does to a connection the client gives up on meanwhile (its watchdog shuts the socket, or
its kernel's ``tcp_user_timeout`` ends it): with ``lose_fin`` (the default, as a real link) the client's
close is lost with the link, and so is what it sent after the freeze began: the server side of that
connection stays open (an orphaned session, ``service.store.sessions``) until the server ends it or the
proxy stops. Without it the close is delivered at the thaw, which hides the orphan (issue 41.1).

``freeze_on(pattern, after=)`` freezes the link at the first chunk a client sends that holds ``pattern``
(e.g. ``b"COMMIT"``) in a transaction that sent ``after`` (e.g. ``b"INSERT INTO samples"``): that chunk is
held like everything else; ``frozen`` is set then.
"""

from __future__ import annotations

import contextlib
import select
import socket
import threading
from dataclasses import dataclass, field


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@dataclass
class _Link:
    client: socket.socket
    upstream: socket.socket | None = None
    abandoned: bool = False  # the client went away while frozen: nothing more goes upstream, not even EOF
    marked: bool = False  # the current transaction sent the trigger's ``after``
    prepared: dict[bytes, bytes] = field(default_factory=dict)  # NUL name NUL -> statement, prepared on it


class TcpProxy:
    """Forward 127.0.0.1:``port`` to ``target``; ``stop()`` closes the listener and every live connection."""

    def __init__(self, port: int, target: tuple[str, int], *, lose_fin: bool = True) -> None:
        self.port = port
        self.target = target
        self.lose_fin = lose_fin
        self._listener: socket.socket | None = None
        self._conns: list[socket.socket] = []
        self._lock = threading.Lock()
        self._flowing = threading.Event()
        self._flowing.set()
        self._trigger: tuple[bytes, bytes | None] | None = None
        self.frozen = threading.Event()  # set by freeze() and by a freeze_on trigger; cleared by thaw()
        self.abandoned = 0  # connections whose close was lost (their server sessions left open)

    def freeze(self) -> None:
        """Stop forwarding without closing anything (new connections are accepted and wait too)."""
        self._flowing.clear()
        self.frozen.set()

    def freeze_on(self, pattern: bytes, *, after: bytes | None = None) -> None:
        """Freeze at the first client chunk holding ``pattern`` in a transaction that sent ``after``."""
        with self._lock:
            self._trigger = (pattern, after)

    def thaw(self) -> None:
        """Forward again, held data first."""
        with self._lock:
            self._trigger = None
        self.frozen.clear()
        self._flowing.set()

    def start(self) -> TcpProxy:
        listener = socket.socket()
        listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        listener.bind(("127.0.0.1", self.port))
        listener.listen(16)
        self._listener = listener
        threading.Thread(target=self._accept, args=(listener,), daemon=True).start()
        return self

    def stop(self) -> None:
        if self._listener is not None:
            with contextlib.suppress(OSError):
                self._listener.shutdown(socket.SHUT_RDWR)
            self._listener.close()
            self._listener = None
        with self._lock:
            conns, self._conns = self._conns, []
        for conn in conns:
            with contextlib.suppress(OSError):
                conn.shutdown(socket.SHUT_RDWR)
            conn.close()
        self._flowing.set()  # let frozen pipe threads run into the closed sockets and end

    def _accept(self, listener: socket.socket) -> None:
        while True:
            try:
                client, _ = listener.accept()
            except OSError:
                return
            with self._lock:
                self._conns.append(client)
            threading.Thread(target=self._connect, args=(_Link(client),), daemon=True).start()

    def _connect(self, link: _Link) -> None:
        # frozen: the client is connected but its startup message goes nowhere
        if not self._wait_flowing(link.client):
            link.client.close()
            return
        try:
            upstream = socket.create_connection(self.target, timeout=5)
        except OSError:
            link.client.close()
            return
        upstream.settimeout(None)
        link.upstream = upstream
        with self._lock:
            self._conns.append(upstream)
        threading.Thread(target=self._pipe_up, args=(link,), daemon=True).start()
        threading.Thread(target=self._pipe_down, args=(link,), daemon=True).start()

    def _wait_flowing(self, src: socket.socket) -> bool:
        """Wait for the thaw; False if ``src`` (a client) closed meanwhile and its close is to be lost."""
        while not self._flowing.wait(0.05):
            if self.lose_fin and _closed(src):
                return False
        return True

    def _check_trigger(self, link: _Link, data: bytes) -> None:
        if b"P" in data:
            link.prepared.update(_named_parses(data))
        with self._lock:
            trigger = self._trigger
            if trigger is None:
                return
            pattern, after = trigger
            if after is not None and (
                after in data or any(name in data for name, q in link.prepared.items() if after in q)
            ):
                link.marked = True
            if pattern in data and (after is None or link.marked):
                self._trigger = None
                self._flowing.clear()
                self.frozen.set()
            elif b"COMMIT" in data or b"ROLLBACK" in data:
                link.marked = False

    def _pipe_up(self, link: _Link) -> None:
        """Client to server: what a client sends while frozen is held; if it then goes away, lost."""
        src, dst = link.client, link.upstream
        assert dst is not None
        try:
            while data := src.recv(65536):
                self._check_trigger(link, data)
                if not self._wait_flowing(src):
                    break
                dst.sendall(data)
        except OSError:
            pass
        if not self._flowing.is_set() and self.lose_fin:
            link.abandoned = True  # frozen: the client's close (and what it held) is lost with the link
            with self._lock:
                self.abandoned += 1
            return
        self._flowing.wait()  # an EOF is not forwarded while frozen either
        with contextlib.suppress(OSError):
            dst.shutdown(socket.SHUT_WR)

    def _pipe_down(self, link: _Link) -> None:
        """Server to client: held while frozen; dropped once the client is gone."""
        src, dst = link.upstream, link.client
        assert src is not None
        try:
            while data := src.recv(65536):
                self._flowing.wait()
                if link.abandoned:
                    continue
                with contextlib.suppress(OSError):
                    dst.sendall(data)
        except OSError:
            pass
        self._flowing.wait()
        with contextlib.suppress(OSError):
            dst.shutdown(socket.SHUT_WR)


def _named_parses(data: bytes) -> dict[bytes, bytes]:
    """{NUL name NUL: statement} of the Parse messages in ``data`` that prepare a named statement (a later
    Bind of it sends the name only: psycopg prepares a statement run 5 times)."""
    out = {}
    p = data.find(b"P")
    while p >= 0:
        length = int.from_bytes(data[p + 1 : p + 5], "big")
        name_end = data.find(b"\0", p + 5)
        query_end = data.find(b"\0", name_end + 1) if name_end > p + 5 else -1
        if query_end > 0 and query_end + 3 <= len(data):
            n_params = int.from_bytes(data[query_end + 1 : query_end + 3], "big")
            if length == query_end + 3 + 4 * n_params - (p + 1):
                out[b"\0" + data[p + 5 : name_end] + b"\0"] = data[name_end + 1 : query_end]
        p = data.find(b"P", p + 1)
    return out


def _closed(sock: socket.socket) -> bool:
    """True if the peer of ``sock`` closed it (EOF or reset), without consuming data."""
    try:
        readable, _, _ = select.select([sock], [], [], 0)
        if not readable:
            return False
        return sock.recv(1, socket.MSG_PEEK) == b""
    except OSError:
        return True
