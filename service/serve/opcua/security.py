"""Who may do what on the OPC UA server (docs/integration.md, "OPC UA security").

asyncua's defaults are wide open (every policy, an ``admin`` user who may write, AddNodes for any session);
this module replaces them:

- :class:`HashedUserManager`: anonymous sessions (if allowed) and users with PBKDF2-SHA256 password hashes
  (``hash_password``; ``chtc opcua user NAME`` prints one), never an administrator. With a Sign&Encrypt-only
  configuration a session must come over a secure channel whose client certificate is in the trust list.
- :class:`ReadOnlyRules`: every session may read, browse and subscribe (and register nodes, which the
  S7-1500's ``OPC_UA_NodeGetHandleList`` uses); only an authenticated user may call a method (the same
  rule as the REST writes: a credential, not anonymity); nobody writes, adds or deletes nodes or
  references: anything not listed is refused.
- :func:`load_trust_list`: the client certificates trusted (a directory of DER or PEM files). A session over
  a secure channel whose client certificate is not among them is refused at ActivateSession
  (``BadCertificateUntrusted``). The check is the user manager's, not asyncua's CreateSession validator:
  that one also judges the certificate a client sends over a None channel, which OPC UA says to ignore
  (Part 4, CreateSession), and so refused every node-opcua client on the None endpoint.
"""

from __future__ import annotations

import hashlib
import hmac
import logging
import secrets
import tomllib
from collections.abc import Mapping
from pathlib import Path

from asyncua import ua
from asyncua.common.utils import ServiceError as UaServiceError
from asyncua.crypto.permission_rules import READ_TYPES, PermissionRuleset
from asyncua.server.users import User, UserRole
from cryptography import x509
from cryptography.hazmat.primitives.serialization import Encoding

from service.serve.errors import OutletError
from service.serve.opcua.refusals import Refusals

__all__ = [
    "HashedUserManager",
    "ReadOnlyRules",
    "hash_password",
    "load_trust_list",
    "load_users",
    "verify_password",
]

log = logging.getLogger(__name__)
SCHEME = "pbkdf2_sha256"
ITERATIONS = 200_000


def hash_password(password: str, *, iterations: int = ITERATIONS, salt: bytes | None = None) -> str:
    """``pbkdf2_sha256$<iterations>$<salt hex>$<hash hex>`` of ``password`` (a random 16-byte salt)."""
    salt = secrets.token_bytes(16) if salt is None else salt
    digest = hashlib.pbkdf2_hmac("sha256", password.encode("utf-8"), salt, iterations)
    return f"{SCHEME}${iterations}${salt.hex()}${digest.hex()}"


def verify_password(password: str, stored: str) -> bool:
    """Whether ``password`` matches the ``stored`` hash (constant-time); False for a malformed hash."""
    try:
        scheme, iterations, salt, digest = stored.split("$")
        if scheme != SCHEME:
            return False
        got = hashlib.pbkdf2_hmac("sha256", password.encode("utf-8"), bytes.fromhex(salt), int(iterations))
    except ValueError:
        return False
    return hmac.compare_digest(got.hex(), digest)


def load_users(users: Mapping[str, str], users_file: Path | None) -> dict[str, str]:
    """The users (name -> hash): ``users`` with the ``[users]`` table of ``users_file`` over them;
    ``OutletError`` names a malformed entry."""
    out = dict(users)
    if users_file is not None:
        try:
            data = tomllib.loads(users_file.read_text(encoding="utf-8"))
        except (OSError, tomllib.TOMLDecodeError) as err:
            raise OutletError(f"opcua.users_file: cannot read {users_file}: {err}") from err
        table = data.get("users", {})
        if not isinstance(table, dict) or not all(isinstance(v, str) for v in table.values()):
            raise OutletError(f'opcua.users_file: {users_file}: expected [users] name = "{SCHEME}$..."')
        out.update(table)
    for name, stored in out.items():
        if not stored.startswith(f"{SCHEME}$") or stored.count("$") != 3:
            raise OutletError(f"opcua.users.{name}: not a {SCHEME} hash (make one with `chtc opcua user`)")
        if name.lower() == "admin":
            raise OutletError(
                "opcua.users: no user may be called admin (asyncua treats it as an administrator)"
            )
    return out


def _der(cert: object) -> bytes | None:
    if cert is None:
        return None
    if isinstance(cert, x509.Certificate):
        return cert.public_bytes(Encoding.DER)
    return bytes(cert)  # type: ignore[call-overload]


def load_trust_list(directory: Path) -> frozenset[bytes]:
    """The DER bytes of every certificate (``*.der``, ``*.pem``, ``*.crt``) in ``directory``."""
    if not directory.is_dir():
        raise OutletError(f"opcua.trust_dir: {directory} is not a directory")
    found = set()
    for path in sorted(directory.iterdir()):
        if path.suffix.lower() not in (".der", ".pem", ".crt"):
            continue
        data = path.read_bytes()
        try:
            cert = (
                x509.load_pem_x509_certificate(data)
                if b"-----BEGIN" in data
                else x509.load_der_x509_certificate(data)
            )
        except ValueError as err:
            raise OutletError(f"opcua.trust_dir: {path} is not a certificate: {err}") from err
        found.add(cert.public_bytes(Encoding.DER))
    return frozenset(found)


class HashedUserManager:
    """asyncua's user manager (see the module docstring): a session over a secure channel needs its client
    certificate in ``trusted``; ``require_trusted``: every session must come over one (a Sign&Encrypt-only
    server: no session over a None channel, which asyncua keeps open for discovery)."""

    def __init__(
        self,
        users: Mapping[str, str],
        *,
        anonymous: bool,
        require_trusted: bool = False,
        trusted: frozenset[bytes] = frozenset(),
    ) -> None:
        self._users = dict(users)
        self.anonymous = anonymous
        self.require_trusted = require_trusted
        self.trusted = trusted

    def get_user(
        self,
        iserver: object,
        username: str | None = None,
        password: str | None = None,
        certificate: object = None,
    ) -> User | None:
        der = _der(certificate)
        if der is None:
            if self.require_trusted:
                return None
        elif der not in self.trusted:
            raise UaServiceError(ua.StatusCodes.BadCertificateUntrusted)
        if username is None:
            return User(role=UserRole.Anonymous) if self.anonymous else None
        stored = self._users.get(username)
        if stored is None or password is None:
            return None
        if isinstance(password, bytes):
            password = password.decode("utf-8", errors="replace")
        return User(role=UserRole.User, name=username) if verify_password(password, stored) else None


class ReadOnlyRules(PermissionRuleset):
    """See the module docstring: read for every session, Call for users, nothing else."""

    def __init__(self, refusals: Refusals | None = None) -> None:
        self.refusals = refusals
        call = ua.NodeId(ua.ObjectIds.CallRequest_Encoding_DefaultBinary)
        self._call = call
        self._read = {ua.NodeId(t) for t in READ_TYPES} - {call}
        self._read |= {  # further read-only services asyncua's list lacks (PLC and SCADA clients use them)
            ua.NodeId(getattr(ua.ObjectIds, f"{name}Request_Encoding_DefaultBinary"))
            for name in (
                "RegisterNodes",
                "UnregisterNodes",
                "BrowseNext",
                "ModifySubscription",
                "SetTriggering",
                "TransferSubscriptions",
            )
        }

    def check_validity(self, user: User, action_type_id: ua.NodeId, body: object) -> bool:
        if user is None or user.role is UserRole.Admin:
            return False
        log.debug("request %s by %s", action_type_id, user)
        if action_type_id in self._read:
            return True
        if action_type_id == self._call and user.role is UserRole.User:
            return True
        if self.refusals is not None:
            client = "anonymous" if user.role is UserRole.Anonymous else f"user {user.name}"
            self.refusals.note(client, _request_name(action_type_id))
        return False


def _request_name(type_id: ua.NodeId) -> str:
    """``Write`` for WriteRequest_Encoding_DefaultBinary (the request a rule refused)."""
    name = ua.ObjectIdNames.get(type_id.Identifier, str(type_id)) if type_id.NamespaceIndex == 0 else ""
    return (name or str(type_id)).removesuffix("_Encoding_DefaultBinary").removesuffix("Request")
