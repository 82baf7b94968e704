"""Fixtures for the OPC UA outlet's tests: certificates made at test time (never committed), the real served
service (``simulator.served``: the demo plan through the real core and shell, a hand-moved clock) with the
OPC UA outlet subscribed to it on loopback, and REST on the same service for comparison."""

from __future__ import annotations

import asyncio
import dataclasses
import socket
from collections.abc import Awaitable, Callable, Iterator
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from asyncua import Client
from asyncua.crypto.cert_gen import (
    dump_private_key_as_pem,
    generate_private_key,
    generate_self_signed_app_certificate,
)
from cryptography import x509
from cryptography.hazmat.primitives.serialization import Encoding
from cryptography.x509.oid import ExtendedKeyUsageOID
from fastapi.testclient import TestClient

from api.app import create_app
from drivers.quality import Quality
from service.serve.opcua.outlet import OpcUaOutlet, opcua_outlet
from service.serve.opcua.security import hash_password
from service.serve.outlet import OutletContext
from service.settings import Settings
from simulator.served import DEMO_FED, Served, served_service

USER, PASSWORD = "plc1", "a-long-test-password"
CLIENT_URI = "urn:freeopcua:client"  # asyncua's client application URI (its certificate must name it)
NS = "urn:spindle-chtc:opcua"
NODE_URI = "urn:spindle-chtc:node-peer"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@dataclass(frozen=True)
class Pki:
    server_cert: Path
    server_key: Path
    trust_dir: Path
    client_cert: Path  # trusted
    client_key: Path
    rogue_cert: Path  # not trusted
    rogue_key: Path
    users_file: Path
    node_cert: Path  # node-opcua's (PEM), trusted
    node_key: Path
    node_rogue_cert: Path  # node-opcua's, not trusted
    node_rogue_key: Path


def make_cert(directory: Path, name: str, *, uri: str, server: bool, pem: bool = False) -> tuple[Path, Path]:
    """A self-signed OPC UA application certificate (DER, or PEM) and its key (PEM) in ``directory``."""
    key = generate_private_key()
    usage = ExtendedKeyUsageOID.SERVER_AUTH if server else ExtendedKeyUsageOID.CLIENT_AUTH
    cert = generate_self_signed_app_certificate(
        key,
        name,
        {"organizationName": "spindle-chtc tests"},
        [x509.UniformResourceIdentifier(uri), x509.DNSName("localhost"), x509.DNSName(socket.gethostname())],
        extended=[usage],
        days=2,
    )
    cert_path = directory / f"{name}-cert.{'pem' if pem else 'der'}"
    key_path = directory / f"{name}-key.pem"
    cert_path.write_bytes(cert.public_bytes(Encoding.PEM if pem else Encoding.DER))
    key_path.write_bytes(dump_private_key_as_pem(key))
    return cert_path, key_path


@pytest.fixture(scope="session")
def pki(tmp_path_factory: pytest.TempPathFactory) -> Pki:
    root = tmp_path_factory.mktemp("opcua-pki")
    (root / "trusted").mkdir()
    server_cert, server_key = make_cert(root, "server", uri="urn:spindle-chtc:server", server=True)
    client_cert, client_key = make_cert(root, "client", uri=CLIENT_URI, server=False)
    rogue_cert, rogue_key = make_cert(root, "rogue", uri=CLIENT_URI, server=False)
    node_cert, node_key = make_cert(root, "node", uri=NODE_URI, server=False, pem=True)
    node_rogue_cert, node_rogue_key = make_cert(root, "node-rogue", uri=NODE_URI, server=False, pem=True)
    (root / "trusted" / "client.der").write_bytes(client_cert.read_bytes())
    (root / "trusted" / "node.pem").write_bytes(node_cert.read_bytes())
    users = root / "users.toml"
    users.write_text(f'[users]\n{USER} = "{hash_password(PASSWORD, iterations=1000)}"\n', encoding="utf-8")
    return Pki(
        *(server_cert, server_key, root / "trusted", client_cert, client_key, rogue_cert, rogue_key, users),
        *(node_cert, node_key, node_rogue_cert, node_rogue_key),
    )


def opcua_settings(
    pki: Pki, *, policies: tuple[str, ...] = ("None", "Basic256Sha256_SignAndEncrypt"), **kw: Any
) -> Settings:
    cfg = {
        "enabled": True,
        "port": free_port(),
        "security_policies": policies,
        "certificate": str(pki.server_cert),
        "private_key": str(pki.server_key),
        "trust_dir": str(pki.trust_dir),
        "users_file": str(pki.users_file),
        "methods": True,
        "update_interval_s": 0.05,
        "refresh_s": 0.2,
        **kw,
    }
    # no [opcua] spindle: the NodeIds follow the spindle's id (ns=2;s=Spindle1.…, as the Node peer reads them)
    return Settings(opcua=cfg, compensation={"reference_c": 20.0}, spindle={"id": "Spindle1"})  # type: ignore[arg-type]


@dataclass
class Rig:
    served: Served
    outlet: OpcUaOutlet
    settings: Settings
    rest: TestClient

    @property
    def url(self) -> str:
        return self.outlet.server.endpoint

    def run(self, fn: Callable[[], Awaitable[Any]]) -> Any:
        return asyncio.run(fn())


def start_rig(tmp: Path, settings: Settings, *, feed: int | None = DEMO_FED) -> Rig:
    served = served_service(
        database_url=f"sqlite:///{tmp / 'opcua.db'}", settings=settings, feed_samples=feed
    )
    try:
        outlet = opcua_outlet(OutletContext(settings=settings, service=served.service, clock=served.clock))
        served.call(outlet.start)
        served.service.subscribe(outlet)
    except BaseException:
        served.close()
        raise
    rest = TestClient(create_app(settings, served.service, clock=served.clock))
    return Rig(served, outlet, settings, rest)


def stop_rig(rig: Rig) -> None:
    try:
        rig.served.call(rig.outlet.close)
    finally:
        rig.served.close()


@pytest.fixture(scope="module")
def rig(tmp_path_factory: pytest.TempPathFactory, pki: Pki) -> Iterator[Rig]:
    """Both endpoints (None and Basic256Sha256 Sign&Encrypt), anonymous and a user, the methods on; the
    tests that read only."""
    r = start_rig(tmp_path_factory.mktemp("opcua-rig"), opcua_settings(pki))
    yield r
    stop_rig(r)


async def node_path(client: Client, path: str) -> Any:
    idx = await client.get_namespace_index(NS)
    return client.get_node(f"ns={idx};s=Spindle1.{path}")


async def next_updates(client: Client, n: int = 2, timeout_s: float = 20.0) -> None:
    """Wait until the server has updated its address space ``n`` more times (Status.Heartbeat)."""
    hb = await node_path(client, "Status.Heartbeat")

    async def beat() -> int:  # Bad_WaitingForInitialData before the first update: -1
        dv = await hb.read_data_value(raise_on_bad_status=False)
        return int(dv.Value.Value) if dv.StatusCode_.is_good() else -1

    start = await beat()
    loop = asyncio.get_running_loop()
    deadline = loop.time() + timeout_s
    while await beat() < start + n:
        assert loop.time() < deadline, "the OPC UA server did not update"
        await asyncio.sleep(0.02)


def daq_lost(s: Any, t: datetime) -> Any:
    """The sample as the acquisition builds it when the DAQ stopped answering: no temperature, CAN alive."""
    return dataclasses.replace(
        s,
        t=t,
        temps_c=np.full_like(s.temps_c, np.nan),
        quality=np.full_like(s.quality, int(Quality.STALE)),
        ambient_c=float("nan"),
        daq_ok=False,
    )
