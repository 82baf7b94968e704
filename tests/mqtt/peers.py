"""The test's own Mosquitto on a free loopback port and the independent Node peer (tests/mqtt/node/peer.js):
real processes, started and stopped by the tests (no mock of the protocol)."""

from __future__ import annotations

import contextlib
import json
import os
import queue
import shutil
import signal
import socket
import subprocess
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

NODE_DIR = Path(__file__).resolve().parent / "node"
MOSQUITTO = shutil.which("mosquitto") or "/usr/sbin/mosquitto"
Line = dict[str, Any]


def need_peers() -> None:
    """Skip when the broker or the Node peer is not installed (.ci/run installs both)."""
    if not Path(MOSQUITTO).exists():
        pytest.skip("mosquitto not installed (.ci/run installs it)")
    if shutil.which("node") is None or not (NODE_DIR / "node_modules" / "sparkplug-payload").is_dir():
        pytest.skip("node or tests/mqtt/node/node_modules missing (npm ci in tests/mqtt/node)")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def wait_port(port: int, *, up: bool, timeout_s: float = 10.0) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        with socket.socket() as s:
            s.settimeout(0.2)
            is_up = s.connect_ex(("127.0.0.1", port)) == 0
        if is_up == up:
            return
        time.sleep(0.05)
    raise TimeoutError(f"port {port} not {'up' if up else 'down'} after {timeout_s} s")


class Broker:
    """Mosquitto on 127.0.0.1:``port`` with persistence in ``workdir`` (a restart keeps the peer's session and
    its queued QoS 0 messages, so the peer sees what was published while it reconnected)."""

    def __init__(self, workdir: Path, *, tls: tuple[Path, Path, Path] | None = None) -> None:
        self.port = free_port()
        self.workdir = workdir
        self.conf = workdir / "mosquitto.conf"
        text = (
            # user root: mosquitto started as root would drop to "mosquitto", which cannot read the test's
            # private temporary directory (certificates, persistence); ignored when not started as root
            f"user root\nper_listener_settings false\nallow_anonymous true\npersistence true\n"
            f"persistence_location {workdir}/\nqueue_qos0_messages true\nlistener {self.port} 127.0.0.1\n"
        )
        self.tls_port: int | None = None
        if tls is not None:  # a second listener with TLS: (CA, server certificate, server key)
            self.tls_port = free_port()
            ca, cert, key = tls
            text += f"listener {self.tls_port} 127.0.0.1\ncafile {ca}\ncertfile {cert}\nkeyfile {key}\n"
        self.conf.write_text(text, encoding="utf-8")
        self.proc: subprocess.Popen[bytes] | None = None

    def start(self) -> None:
        log = (self.workdir / "mosquitto.log").open("ab")
        self.proc = subprocess.Popen([MOSQUITTO, "-c", str(self.conf)], stdout=log, stderr=log)
        wait_port(self.port, up=True)

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.terminate()
            self.proc.wait(timeout=10)
        self.proc = None
        wait_port(self.port, up=False)

    @property
    def url(self) -> str:
        return f"mqtt://127.0.0.1:{self.port}"


@contextlib.contextmanager
def broker(workdir: Path, *, tls: tuple[Path, Path, Path] | None = None) -> Iterator[Broker]:
    b = Broker(workdir, tls=tls)
    b.start()
    try:
        yield b
    finally:
        b.stop()


class Peer:
    """``node peer.js``: every decoded message as a dict, in order (``lines``), waited for with a deadline."""

    def __init__(self, argv: list[str]) -> None:
        self.proc = subprocess.Popen(
            ["node", str(NODE_DIR / "peer.js"), *argv],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            start_new_session=True,
        )
        self.lines: list[Line] = []
        self._q: queue.Queue[Line] = queue.Queue()
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for raw in self.proc.stdout:
            self._q.put(json.loads(raw))

    def _pull(self, timeout_s: float) -> Line | None:
        try:
            line = self._q.get(timeout=timeout_s)
        except queue.Empty:
            return None
        self.lines.append(line)
        return line

    def wait_for(self, pred: Callable[[Line], bool], timeout_s: float = 15.0, what: str = "") -> Line:
        """The first line read from now on that matches ``pred`` (earlier lines stay in ``lines``)."""
        deadline = time.monotonic() + timeout_s
        while (left := deadline - time.monotonic()) > 0:
            line = self._pull(min(left, 0.5))
            if line is not None and pred(line):
                return line
            if self.proc.poll() is not None and self._q.empty():
                err = self.proc.stderr.read().decode() if self.proc.stderr else ""
                raise AssertionError(f"peer exited: {err}")
        raise AssertionError(f"no {what or 'matching message'} within {timeout_s} s; last: {self.lines[-5:]}")

    def send(self, line: str) -> None:
        assert self.proc.stdin is not None
        self.proc.stdin.write(line.encode() + b"\n")
        self.proc.stdin.flush()

    def close(self) -> None:
        if self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGTERM)
            self.proc.wait(timeout=10)


@contextlib.contextmanager
def peer(*argv: str) -> Iterator[Peer]:
    p = Peer(list(argv))
    try:
        p.wait_for(lambda ln: ln.get("event") == "ready", what="subscription")
        yield p
    finally:
        p.close()


def kind(k: str) -> Callable[[Line], bool]:
    return lambda ln: ln.get("kind") == k


def metrics_by_name(line: Line) -> dict[str, Line]:
    return {m["name"]: m for m in line["payload"]["metrics"]}


def make_certificates(into: Path) -> tuple[Path, Path, Path]:
    """A throw-away CA and a server certificate for 127.0.0.1 signed by it (openssl): (ca, cert, key)."""
    if shutil.which("openssl") is None:
        pytest.skip("openssl not installed")
    ca, ca_key = into / "ca.pem", into / "ca.key"
    cert, key, csr, ext = into / "server.pem", into / "server.key", into / "server.csr", into / "san.ext"
    ext.write_text("subjectAltName=IP:127.0.0.1\n", encoding="ascii")
    days, rsa = ["-days", "1"], ["-newkey", "rsa:2048", "-nodes"]
    for argv in (
        ["req", "-x509", *rsa, "-keyout", ca_key, "-out", ca, *days, "-subj", "/CN=ca"],
        ["req", *rsa, "-keyout", key, "-out", csr, "-subj", "/CN=127.0.0.1"],
        [
            "x509",
            "-req",
            "-in",
            csr,
            "-CA",
            ca,
            "-CAkey",
            ca_key,
            "-CAcreateserial",
            "-out",
            cert,
            *days,
            "-extfile",
            ext,
        ],
    ):
        subprocess.run(["openssl", *map(str, argv)], check=True, capture_output=True)
    return ca, cert, key
