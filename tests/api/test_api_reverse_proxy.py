"""deploy/nginx/chtc.conf: nginx accepts it (``nginx -t``) and, on loopback in front of a live API, serves
TLS, redirects plain HTTP and answers its own refusals in the API's error shape.

Only the addresses, ports and certificate paths are replaced (each replacement is checked, so the test
notices when the file changes); the limits are the file's own. Skipped when nginx is not installed
(Debian: ``apt install nginx-light``).
"""

from __future__ import annotations

import os
import shutil
import socket
import ssl
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from api.app import create_app
from service.settings import Settings
from service.shell.service import SoftSensorService
from tests.api.conftest import WRITE_TOKEN, LiveServer, ManualClock, free_port

CONF = Path(__file__).resolve().parents[2] / "deploy" / "nginx" / "chtc.conf"
NGINX = shutil.which("nginx") or ("/usr/sbin/nginx" if Path("/usr/sbin/nginx").exists() else None)
pytestmark = pytest.mark.skipif(NGINX is None, reason="nginx is not installed")


def _self_signed(tmp: Path) -> tuple[Path, Path]:
    cert, key = tmp / "cert.pem", tmp / "key.pem"
    subprocess.run(
        ["openssl", "req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes",
         "-days", "1", "-subj", "/CN=127.0.0.1", "-addext", "subjectAltName=IP:127.0.0.1",
         "-keyout", str(key), "-out", str(cert)],
        check=True, capture_output=True, timeout=30,
    )  # fmt: skip
    return cert, key


def _site(tmp: Path, *, tls: int, plain: int, api: int) -> Path:
    cert, key = _self_signed(tmp)
    text = CONF.read_text()
    for old, new in [
        ("listen 443 ssl http2;", f"listen 127.0.0.1:{tls} ssl http2;"),
        ("listen 80;", f"listen 127.0.0.1:{plain};"),
        ("server 127.0.0.1:8000;", f"server 127.0.0.1:{api};"),
        ("/etc/ssl/certs/chtc.pem", str(cert)),
        ("/etc/ssl/private/chtc.key", str(key)),
    ]:
        assert text.count(old) == 1, f"deploy/nginx/chtc.conf no longer has {old!r}"
        text = text.replace(old, new)
    site = tmp / "chtc.conf"
    site.write_text(text)
    main = tmp / "nginx.conf"
    user = "user root;\n" if os.geteuid() == 0 else ""  # workers must read the test's private files
    temp = " ".join(f"{k}_temp_path {tmp / k};" for k in ("client_body", "proxy", "fastcgi", "uwsgi", "scgi"))
    main.write_text(
        f"{user}worker_processes 1;\ndaemon off;\npid {tmp / 'nginx.pid'};\n"
        f"error_log {tmp / 'error.log'} warn;\n"
        f"events {{ worker_connections 256; }}\n"
        f"http {{ access_log off; {temp} include {site}; }}\n"
    )
    return main


def _wait_port(port: int, proc: subprocess.Popen[bytes], timeout_s: float = 10.0) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        assert proc.poll() is None, "nginx exited"
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=0.2):
                return
        except OSError:
            time.sleep(0.05)
    raise AssertionError(f"nginx did not listen on {port}")


@pytest.fixture
def proxy(tmp_path: Path, service: SoftSensorService, clock: ManualClock) -> Iterator[tuple[int, int, Path]]:
    app = create_app(Settings(api={"token": WRITE_TOKEN}), service, clock=clock)
    with LiveServer(app) as api:
        tls, plain = free_port(), free_port()
        main = _site(tmp_path, tls=tls, plain=plain, api=api.port)
        check = subprocess.run(
            [NGINX, "-t", "-c", str(main), "-p", str(tmp_path)], capture_output=True, timeout=30
        )  # type: ignore[list-item]
        assert check.returncode == 0, check.stderr.decode()
        proc = subprocess.Popen([NGINX, "-c", str(main), "-p", str(tmp_path)], stderr=subprocess.PIPE)  # type: ignore[list-item]
        try:
            _wait_port(tls, proc)
            yield tls, plain, tmp_path / "cert.pem"
        finally:
            proc.terminate()
            proc.wait(timeout=10)


def test_nginx_accepts_the_example_and_proxies_over_tls(proxy: tuple[int, int, Path]) -> None:
    tls, plain, cert = proxy
    ctx = ssl.create_default_context(cafile=str(cert))
    with httpx.Client(base_url=f"https://127.0.0.1:{tls}", verify=ctx, timeout=10) as c:
        r = c.get("/api/v1/chtc")
        assert r.status_code == 200 and r.headers["etag"]
        assert r.headers["strict-transport-security"].startswith("max-age=")
        # the write path works through the proxy (token passed on)
        ok = c.post(
            "/api/v1/identifications",
            json={"reason": "proxy"},
            headers={"Authorization": f"Bearer {WRITE_TOKEN}"},
        )
        assert ok.status_code == 202, ok.text
        # nginx refuses a body over 4 KiB itself, in the API's shape
        big = c.post(
            "/api/v1/identifications", content=b"x" * 10_000, headers={"Content-Type": "application/json"}
        )
        assert big.status_code == 413
        assert big.json()["error"]["code"] == "too_large"
        # an over-long request target never reaches the service
        long = c.get("/api/v1/sensors?channels=" + "9" * 40_000)
        assert long.status_code == 414 and long.json()["error"]["code"] == "uri_too_long"
    redirect = httpx.get(f"http://127.0.0.1:{plain}/api/v1/chtc", timeout=10)
    assert redirect.status_code == 301
    assert redirect.headers["location"].startswith("https://")
