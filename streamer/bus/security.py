"""Credentials and access control of a run: mutual TLS and Zenoh's access-control list.

Every session of a run talks TLS with a certificate of the run's own certificate
authority (CA), and every router checks the certificate of each peer (mutual TLS,
``transport/link/tls/enable_mtls``) and applies an access-control list keyed by the
certificate's common name (``access_control`` of Zenoh's configuration, built by
:func:`streamer.bus.access_control.access_control`; see
``DEFAULT_CONFIG.json5`` of eclipse-zenoh).  Identities (common names, :data:`ROLES`):

``replayer``, ``tdi_builder``, ``fitter``, ``subtractor``, ``monitor``
    a stage: may publish its own output topic (``ttl/<run>/<topic>``), its own progress
    (``ttl/<run>/control/progress/<stage>``), its own liveliness token
    (``ttl/<run>/alive/<stage>``) and errors (``ttl/<run>/errors/<i>``), and answer the
    commands sent to it (a queryable on ``ttl/<run>/control/<stage>/*``); it may not ask
    another stage's commands (a query there is a command);
``launcher``
    ``ttl run``: may publish commands (``ttl/<run>/control/...``, progress excepted), the
    progress it verified (``ttl/<run>/control/board/<stage>``, advanced publishers) and its
    own liveliness token ``ttl/<run>/alive/launcher``;
``control``
    ``ttl control`` (an operator): commands to stages (puts, and queries answered with the
    stage's verdict), progress excepted;
``router``
    the routers (``ttl router``, the router started by ``ttl run``): a router forwards what
    the stages behind it published, so it may publish everything of the project.

Every identity may subscribe and query (read), a stage's command keys excepted for the
stages; nothing else is allowed (default deny).
A router refuses a peer whose certificate is missing or not signed by the run's CA (the
TLS handshake fails) and drops a publication its ACL forbids; both are written to the
router's log (:data:`ROUTER_LOG_FILTER`), which :func:`refusals` reads back.

Files of a credentials directory (:func:`ensure_credentials`): ``ca.pem`` (the CA
certificate, public), ``ca.key`` (the CA key: only needed to issue certificates), and
``<role>.pem``, ``<role>.key`` per identity.  Keys are written mode 0600, the directory is
0700.  The router certificate names the addresses routers are reached at (127.0.0.1,
``localhost`` and the ``hosts`` given), which clients check (``verify_name_on_connect``);
the other certificates name no address, so a stage cannot pose as a router.
"""

from __future__ import annotations

import datetime as _dt
import ipaddress
import json
import os
import re
import stat
import threading
from dataclasses import dataclass
from pathlib import Path

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import dsa, ec, ed448, ed25519, rsa
from cryptography.hazmat.primitives.asymmetric.types import CertificateIssuerPrivateKeyTypes
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from ttlcore.errors import TTLError

from .access_control import ROLES  # every identity a credentials directory holds a certificate for

#: Addresses always in the router certificate.
LOCAL_HOSTS = ("127.0.0.1", "localhost")
#: Validity of generated certificates [days].
VALIDITY_DAYS = 365
#: RUST_LOG filter of a router process: TLS connections accepted or refused (zenoh_link_tls
#: logs them at debug/warn) and ACL decisions (zenoh logs them at trace level).
ROUTER_LOG_FILTER = "warn,zenoh_link_tls=debug,zenoh::net::routing::interceptor::access_control=trace"

#: Private keys a CA key may be (ours is EC; a key of another kind cannot sign certificates).
SIGNING_KEYS = (
    ec.EllipticCurvePrivateKey,
    rsa.RSAPrivateKey,
    dsa.DSAPrivateKey,
    ed25519.Ed25519PrivateKey,
    ed448.Ed448PrivateKey,
)


class CredentialsError(TTLError):
    """Credentials are missing, unreadable or unsafe (message names the file)."""


# ---------------------------------------------------------------------------- generation


def _write_private(path: Path, data: bytes, mode: int = 0o600) -> None:
    """Write ``data`` to ``path`` atomically, created with ``mode`` (never readable by others)."""
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    tmp.unlink(missing_ok=True)
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, mode)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def _name(common_name: str):
    return x509.Name(
        [
            x509.NameAttribute(NameOID.ORGANIZATION_NAME, "ttl-streamer"),
            x509.NameAttribute(NameOID.COMMON_NAME, common_name),
        ]
    )


def _san(hosts):
    names: list[x509.GeneralName] = []
    for h in dict.fromkeys(hosts):
        try:
            names.append(x509.IPAddress(ipaddress.ip_address(h)))
        except ValueError:
            names.append(x509.DNSName(h))
    return x509.SubjectAlternativeName(names)


def _cert_hosts(cert) -> set[str]:
    try:
        san = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    except x509.ExtensionNotFound:
        return set()
    return {str(v) for v in san.get_values_for_type(x509.IPAddress)} | set(san.get_values_for_type(x509.DNSName))


def _key_usage(ca: bool):
    return x509.KeyUsage(
        digital_signature=True,
        key_cert_sign=ca,
        crl_sign=ca,
        content_commitment=False,
        key_encipherment=False,
        data_encipherment=False,
        key_agreement=False,
        encipher_only=False,
        decipher_only=False,
    )


def _pem_key(key) -> bytes:
    return key.private_bytes(
        serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
    )


def _load_cert(path: Path):
    try:
        return x509.load_pem_x509_certificate(path.read_bytes())
    except (OSError, ValueError) as exc:
        raise CredentialsError(f"{path}: not a readable PEM certificate ({exc})") from None


def ensure_credentials(directory, hosts=(), roles=ROLES) -> Path:
    """Create what is missing of a credentials directory; returns it.

    A CA (EC P-256, self-signed, ``ca.pem``/``ca.key``) is made on first use; then one
    certificate per role in ``roles`` (common name = role, signed by the CA, valid
    :data:`VALIDITY_DAYS`).  Existing files are kept; the router certificate is reissued
    when it does not name every address of ``hosts``.

    Parameters
    ----------
    directory : path
        Created mode 0700 when missing.
    hosts : sequence of str
        Addresses (IP or DNS names) routers listen on, besides :data:`LOCAL_HOSTS`.
    roles : sequence of str
        Identities to issue certificates for.

    Raises
    ------
    CredentialsError
        If a certificate is needed but the CA key is absent (a directory copied to a
        stage host holds no CA key), or a file is unreadable.
    """
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True, mode=0o700)
    now = _dt.datetime.now(_dt.UTC)
    start, end = now - _dt.timedelta(minutes=10), now + _dt.timedelta(days=VALIDITY_DAYS)
    ca_pem, ca_key_path = d / "ca.pem", d / "ca.key"
    router_hosts = (*LOCAL_HOSTS, *hosts)
    todo = _to_issue(d, roles, router_hosts)
    if not todo and ca_pem.exists():
        return d
    if not ca_pem.exists():
        _new_ca(ca_pem, ca_key_path, start, end)
    if not todo:
        return d
    if not ca_key_path.exists():
        raise CredentialsError(
            f"{ca_key_path}: missing: cannot issue certificate(s) for {', '.join(todo)} "
            "(issue them where the CA key is kept, then copy them here)"
        )
    check_private(ca_key_path)
    ca = _load_cert(ca_pem)
    ca_key = _load_ca_key(ca_key_path)
    for role in todo:
        _issue(d, role, ca, ca_key, (start, end), router_hosts)
    return d


def _to_issue(d: Path, roles, router_hosts: tuple[str, ...]) -> list[str]:
    """The roles of ``roles`` whose certificate or key is missing from ``d``, and the router
    when its certificate does not name every host of ``router_hosts``."""
    todo = []
    for role in roles:
        pem, key = d / f"{role}.pem", d / f"{role}.key"
        if not pem.exists() or not key.exists():
            todo.append(role)
        elif role == "router" and not set(router_hosts) <= _cert_hosts(_load_cert(pem)):
            todo.append(role)
    return todo


def _new_ca(ca_pem: Path, ca_key_path: Path, start: _dt.datetime, end: _dt.datetime) -> None:
    """A new CA: its key and self-signed certificate, valid from ``start`` to a day after ``end``."""
    if ca_key_path.exists():
        raise CredentialsError(f"{ca_key_path}: a CA key without its certificate ca.pem")
    ca_key = ec.generate_private_key(ec.SECP256R1())
    ca = (
        x509.CertificateBuilder()
        .subject_name(_name("ttl-streamer CA"))
        .issuer_name(_name("ttl-streamer CA"))
        .public_key(ca_key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(start)
        .not_valid_after(end + _dt.timedelta(days=1))
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(_key_usage(ca=True), critical=True)
        .sign(ca_key, hashes.SHA256())
    )
    _write_private(ca_key_path, _pem_key(ca_key))
    _write_private(ca_pem, ca.public_bytes(serialization.Encoding.PEM), 0o644)


def _load_ca_key(path: Path) -> CertificateIssuerPrivateKeyTypes:
    """The CA key of ``path``; a CredentialsError when unreadable or unable to sign certificates."""
    try:
        loaded = serialization.load_pem_private_key(path.read_bytes(), password=None)
    except (OSError, ValueError) as exc:
        raise CredentialsError(f"{path}: not a readable private key ({exc})") from None
    if not isinstance(loaded, SIGNING_KEYS):
        raise CredentialsError(f"{path}: a {type(loaded).__name__}, which cannot sign certificates")
    return loaded


def _issue(
    d: Path,
    role: str,
    ca: x509.Certificate,
    ca_key: CertificateIssuerPrivateKeyTypes,
    validity: tuple[_dt.datetime, _dt.datetime],
    router_hosts: tuple[str, ...],
) -> None:
    """A new key and certificate for ``role`` in ``d``, signed by the CA (the router's for
    TLS servers too, naming ``router_hosts``)."""
    role_key = ec.generate_private_key(ec.SECP256R1())
    usage = [ExtendedKeyUsageOID.CLIENT_AUTH]
    builder = (
        x509.CertificateBuilder()
        .subject_name(_name(role))
        .issuer_name(ca.subject)
        .public_key(role_key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(validity[0])
        .not_valid_after(validity[1])
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(_key_usage(ca=False), critical=True)
    )
    if role == "router":  # the only identity that listens
        usage.insert(0, ExtendedKeyUsageOID.SERVER_AUTH)
        builder = builder.add_extension(_san(router_hosts), critical=False)
    cert = builder.add_extension(x509.ExtendedKeyUsage(usage), critical=False).sign(ca_key, hashes.SHA256())
    _write_private(d / f"{role}.key", _pem_key(role_key))
    _write_private(d / f"{role}.pem", cert.public_bytes(serialization.Encoding.PEM), 0o644)


def check_private(path: Path) -> Path:
    """``path`` exists and is readable by its owner only (else :class:`CredentialsError`)."""
    try:
        mode = path.stat().st_mode
    except OSError as exc:
        raise CredentialsError(f"{path}: {exc.strerror or exc}") from None
    if mode & (stat.S_IRWXG | stat.S_IRWXO):
        raise CredentialsError(
            f"{path}: private key readable by others (mode {stat.S_IMODE(mode):o}); chmod 600 {path}"
        )
    return path


@dataclass(frozen=True)
class Identity:
    """The files of one identity of a credentials directory."""

    directory: Path
    role: str

    @property
    def ca(self) -> Path:
        return self.directory / "ca.pem"

    @property
    def certificate(self) -> Path:
        return self.directory / f"{self.role}.pem"

    @property
    def key(self) -> Path:
        return self.directory / f"{self.role}.key"

    def check(self) -> Identity:
        """Every file present, the key private (else :class:`CredentialsError` naming the file)."""
        for p in (self.ca, self.certificate):
            if not p.is_file():
                raise CredentialsError(f"{p}: missing (credentials of {self.role!r}; 'ttl credentials' makes them)")
        check_private(self.key)
        return self

    def tls(self, listen: bool) -> dict:
        """``transport/link/tls`` of a Zenoh configuration: mutual TLS with this identity."""
        self.check()
        tls = {
            "root_ca_certificate": str(self.ca.resolve()),
            "enable_mtls": True,
            "connect_certificate": str(self.certificate.resolve()),
            "connect_private_key": str(self.key.resolve()),
            "verify_name_on_connect": True,
        }
        if listen:
            tls.update(listen_certificate=str(self.certificate.resolve()), listen_private_key=str(self.key.resolve()))
        return tls


# ---------------------------------------------------------------------------- refusals in a router log

_ANSI = re.compile(r"\x1b\[[0-9;]*m")
_DENIED = re.compile(r"(?P<zid>[0-9a-f]+) on (?P<subject>\S+) is unauthorized to (?P<action>.+?) on (?P<key>\S+)\s*$")
_CACHED = re.compile(r"Using cached result: (?P<zid>[0-9a-f]+) is unauthorized to (?P<action>.+?) on (?P<key>\S+)\s*$")
_CACHING = re.compile(r"caching permissions for `(?P<key>[^`]*)`")
_THREAD = re.compile(r"ThreadId\((\d+)\)")
_CN = re.compile(r"CertCommonName\(([^)]*)\)")
_TIME = re.compile(r"^(\d{4}-\d\d-\d\dT[0-9:.]+Z)")
#: Handshake failures of zenoh_link_tls (a peer without a valid certificate, or not TLS).
#: "received fatal alert" is the peer refusing the router's certificate: ``UnknownCA`` (it
#: trusts another CA), ``DecryptError`` (it trusts another CA of the same name: the signature
#: does not verify), ``BadCertificate``...  (A peer presenting a certificate of the run's CA
#: with another key is refused without a log line from zenoh 1.10: not recorded.)
_HANDSHAKE = (
    "invalid peer certificate",
    "Can not accept TLS connection",
    "received corrupt message",
    "peer sent no certificates",
    "CertificateRequired",
    "received fatal alert",
)


class RefusalParser:
    """Reads a router's log (:data:`ROUTER_LOG_FILTER`) line by line and returns the refusals.

    A refusal is ``{"kind": "forbidden", "subject", "action", "key", "time"}`` (a message
    the ACL dropped; ``subject`` is the certificate's common name) or
    ``{"kind": "unauthenticated", "message", "time"}`` (a TLS handshake refused).

    Zenoh logs ACL decisions at trace level in two situations: when a key is declared it
    computes (and logs) the permission of every message type for it ("caching permissions
    for ..."): not refusals; then each message dropped is logged with its decision (cached
    or not): refusals.
    """

    def __init__(self):
        self.names: dict[str, str] = {}  # zid -> common name
        self._caching: dict[str, tuple] = {}  # thread -> (key being cached, actions seen)

    def feed(self, lines) -> list[dict]:
        out = []
        for raw in lines:
            line = _ANSI.sub("", raw).rstrip()
            t = _TIME.match(line)
            when = t.group(1) if t else None
            th = _THREAD.search(line)
            thread = th.group(1) if th else ""
            c = _CACHING.search(line)
            if c:
                self._caching[thread] = (c.group("key"), set())
                continue
            m = _DENIED.search(line)
            if m:
                cn = _CN.search(m.group("subject"))
                name = cn.group(1) if cn else m.group("subject")
                self.names[m.group("zid")] = name
                key, seen = self._caching.get(thread, (None, set()))
                if key == m.group("key") and m.group("action") not in seen:
                    seen.add(m.group("action"))  # a permission computed for a declared key, not a message
                    continue
                self._caching.pop(thread, None)
                out.append(
                    {
                        "kind": "forbidden",
                        "subject": name,
                        "action": m.group("action"),
                        "key": m.group("key"),
                        "time": when,
                    }
                )
                continue
            if _ALLOWED.search(line):
                continue
            self._caching.pop(thread, None)
            m = _CACHED.search(line)
            if m:
                out.append(
                    {
                        "kind": "forbidden",
                        "subject": self.names.get(m.group("zid"), m.group("zid")),
                        "action": m.group("action"),
                        "key": m.group("key"),
                        "time": when,
                    }
                )
            elif "zenoh_link_tls" in line and any(h in line for h in _HANDSHAKE):
                message = line.split("zenoh_link_tls::unicast:", 1)[-1].strip()
                out.append({"kind": "unauthenticated", "message": message.split(". Hint:")[0], "time": when})
        return out


def refusals(lines) -> list[dict]:
    """Every refusal of a router log (see :class:`RefusalParser`)."""
    return RefusalParser().feed(lines)


class RefusalWatcher:
    """Reads the new lines of a router log and returns the refusals found in them."""

    def __init__(self, path, offset: int = 0):
        self.path = Path(path)
        self._offset = offset
        self._partial = ""
        self._parser = RefusalParser()

    def poll(self) -> list[dict]:
        try:
            with open(self.path, "rb") as f:
                f.seek(self._offset)
                data = f.read()
        except OSError:
            return []
        self._offset += len(data)
        text = self._partial + data.decode("utf-8", errors="replace")
        lines = text.split("\n")
        self._partial = lines.pop()
        return self._parser.feed(lines)


#: Lines a router's log does not keep: the ACL decisions that allowed a message (one per
#: message at trace level).
_ALLOWED = re.compile(r" is authorized to ")


def filter_log() -> None:
    """Pass this process's stdout and stderr (where Zenoh logs) through threads that drop
    the allowed-message decisions (:data:`_ALLOWED`), so that a router's log keeps its
    refusals without growing with every message."""

    for fd in (1, 2):
        read_fd, write_fd = os.pipe()
        real = os.dup(fd)
        os.dup2(write_fd, fd)
        os.close(write_fd)
        threading.Thread(target=_pump, args=(read_fd, real), name=f"router-log-{fd}", daemon=True).start()


def _pump(read_fd: int, real_fd: int) -> None:
    with os.fdopen(read_fd, "rb", buffering=0) as src, os.fdopen(real_fd, "wb", buffering=0) as dst:
        pending = b""
        while True:
            chunk = src.read(65536)
            if not chunk:
                break
            pending += chunk
            *lines, pending = pending.split(b"\n")
            kept = [ln for ln in lines if not _ALLOWED.search(ln.decode("utf-8", "replace"))]
            if kept:
                dst.write(b"\n".join(kept) + b"\n")
        if pending:
            dst.write(pending)


def dump(records, path) -> Path:
    """Write refusal records as JSON lines (``security.jsonl`` of a run), atomically."""
    path = Path(path)
    _write_private(path, "".join(json.dumps(r) + "\n" for r in records).encode(), 0o644)
    return path


def endpoint_host(endpoint: str) -> str | None:
    """The host of a Zenoh endpoint (``tls/198.18.0.1:7447`` -> ``198.18.0.1``; None if unparsable)."""
    m = re.match(r"^[a-z0-9-]+/(\[[^\]]+\]|[^:/#?]+):\d+", str(endpoint))
    return m.group(1).strip("[]") if m else None
