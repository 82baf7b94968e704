"""What the OPC UA server needs from files, checked before the model loads (``chtc run``, ``chtc demo``).

Without it, an unreadable certificate or key was found by asyncua at the server's start, after the model
had loaded (about 10 s), and ended in tracebacks. :func:`check_opcua_files` raises ``OutletError`` with one
line naming the setting: ``opcua.certificate``, ``opcua.private_key``, ``opcua.trust_dir``,
``opcua.users_file``.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

from cryptography import x509
from cryptography.hazmat.primitives.serialization import load_der_private_key, load_pem_private_key

from service.serve.errors import OutletError
from service.serve.opcua.security import load_trust_list, load_users

if TYPE_CHECKING:
    from service.settings import OpcUaSettings

__all__ = ["check_opcua_files"]


def _read(path: Path, setting: str) -> bytes:
    try:
        return path.read_bytes()
    except OSError as err:
        raise OutletError(f"{setting}: cannot read {path}: {err.strerror or err}") from err


def check_opcua_files(cfg: OpcUaSettings) -> None:
    """Raise ``OutletError`` naming the setting unless every file the server will load is readable and what
    it should be (a certificate, a private key without a password, a directory of certificates, users)."""
    if cfg.certificate is not None:
        data = _read(cfg.certificate, "opcua.certificate")
        try:
            if b"-----BEGIN" in data:
                x509.load_pem_x509_certificate(data)
            else:
                x509.load_der_x509_certificate(data)
        except ValueError as err:
            raise OutletError(f"opcua.certificate: {cfg.certificate} is not a certificate: {err}") from err
    if cfg.private_key is not None:
        data = _read(cfg.private_key, "opcua.private_key")
        try:
            if b"-----BEGIN" in data:
                load_pem_private_key(data, password=None)
            else:
                load_der_private_key(data, password=None)
        except (ValueError, TypeError) as err:
            raise OutletError(
                f"opcua.private_key: {cfg.private_key} is not a private key without a password: {err}"
            ) from err
    if cfg.trust_dir is not None:
        load_trust_list(cfg.trust_dir)
    load_users({k: v.get_secret_value() for k, v in cfg.users.items()}, cfg.users_file)
