"""The certificates of the stack's Zenoh links over TLS: a small certificate authority.

With TLS and mutual authentication (``transport/link/tls``, ``enable_mtls: true``) the
router checks each client's certificate against the stack's CA and its access-control
list names a client by the certificate's common name (``cert_common_names``): an
identity no one can declare for itself, and no password to hand around. Zenoh's TLS is
rustls, so every certificate is X.509 v3 with a subjectAltName, the keys PEM (PKCS8),
ECDSA P-256.

``write_certs`` lays a folder out (``aesop zenoh certs DIR --robot robot0 --server-name
server.lan``)::

    ca.pem, ca-key.pem          the CA (its key 0600; no key when the operator's CA is used)
    router.pem, router-key.pem  the server router: serverAuth and clientAuth, SAN = the
                                server names, localhost, 127.0.0.1 and ::1
    <service>.pem, -key.pem     each of the server's own sessions: clientAuth
    robot-<id>/                 (0700) what robot <id>'s computer needs and nothing else:
                                ca.pem, robot-<id>.pem, robot-<id>-key.pem (clientAuth)

It can run again: the CA is kept and so is every certificate still good (same CA, same
names, more than 30 days left), so adding a robot later invalidates no one.
"""

from __future__ import annotations

import datetime
import ipaddress
import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TypeAlias

from cryptography import x509
from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec, ed25519, rsa
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from tools.stack.acl import write_file, write_private

# the keys a CA may sign with here: ours are EC P-256, an operator's may be RSA or Ed25519
# too (what rustls verifies; not DSA or Ed448)
PrivateKey: TypeAlias = ec.EllipticCurvePrivateKey | rsa.RSAPrivateKey | ed25519.Ed25519PrivateKey
_SIGNERS = (ec.EllipticCurvePrivateKey, rsa.RSAPrivateKey, ed25519.Ed25519PrivateKey)
Certificate: TypeAlias = x509.Certificate

ROUTER = "router"  # the server router's cert name
LOCAL_NAMES = ("localhost", "127.0.0.1", "::1")  # the router's, always: a client on the server
RENEW_BEFORE = datetime.timedelta(days=30)  # a cert expiring sooner is issued again
# certificates start an hour back: a robot's clock a little behind the server's still
# accepts one issued just now
BACKDATE = datetime.timedelta(hours=1)
COMMAND = "aesop zenoh certs"

_NAME = re.compile(r"^[A-Za-z0-9_-]+$")
_LABEL = re.compile(r"^(?!-)[A-Za-z0-9-]{1,63}(?<!-)$")


@dataclass(frozen=True)
class CertLayout:
    """Where ``write_certs`` put everything; ``issued`` names the certificates it issued
    on this run (the rest were kept)."""

    folder: Path
    robots: tuple[str, ...] = ()
    services: tuple[str, ...] = ()
    issued: tuple[str, ...] = ()

    @property
    def ca(self) -> Path:
        return self.folder / "ca.pem"

    @property
    def ca_key(self) -> Path:
        """The stack's own CA key (absent when issuing from an operator's CA)."""
        return self.folder / "ca-key.pem"

    def cert(self, name: str) -> Path:
        """The certificate of ``name`` (the router or a service) on the server."""
        return self.folder / f"{name}.pem"

    def key(self, name: str) -> Path:
        return self.folder / f"{name}-key.pem"

    @property
    def router(self) -> Path:
        return self.cert(ROUTER)

    @property
    def router_key(self) -> Path:
        return self.key(ROUTER)

    def robot_folder(self, robot: str) -> Path:
        """What to copy to robot ``robot``'s computer."""
        return self.folder / robot_name(robot)

    def robot_ca(self, robot: str) -> Path:
        return self.robot_folder(robot) / "ca.pem"

    def robot_cert(self, robot: str) -> Path:
        return self.robot_folder(robot) / f"{robot_name(robot)}.pem"

    def robot_key(self, robot: str) -> Path:
        return self.robot_folder(robot) / f"{robot_name(robot)}-key.pem"


def robot_name(robot: str) -> str:
    """A robot's certificate common name: the user name of tools/stack/acl.py too."""
    return f"robot-{robot}"


def check_name(name: str, what: str = "name") -> str:
    """A robot id or service name: letters, digits, ``_`` and ``-`` (it becomes a file
    name and a common name)."""
    if not _NAME.match(name):
        raise ValueError(f"bad {what} {name!r}: use letters, digits, '_' and '-' only")
    return name


def check_server_name(name: str) -> str:
    """A DNS name (a leading ``*.`` allowed) or an IP address, as it goes into a SAN."""
    try:
        return str(ipaddress.ip_address(name))
    except ValueError:
        pass
    host = name.removesuffix(".")
    labels = host.split(".")
    if labels[0] == "*" and len(labels) > 1:
        labels = labels[1:]
    if (not host or len(host) > 253 or not all(_LABEL.match(label) for label in labels)
            or labels[-1].isdigit()):  # all digits at the end: a mistyped IP address
        raise ValueError(f"bad server name {name!r}: neither a DNS name nor an IP address")
    return host.lower()


def san_of(names: Sequence[str]) -> list[x509.GeneralName]:
    """Each name as an IPAddress when it parses as one, else a DNSName (no duplicates)."""
    out: list[x509.GeneralName] = []
    for name in names:
        try:
            entry: x509.GeneralName = x509.IPAddress(ipaddress.ip_address(name))
        except ValueError:
            entry = x509.DNSName(name)
        if entry not in out:
            out.append(entry)
    return out


def _now() -> datetime.datetime:
    return datetime.datetime.now(datetime.UTC)


def _new_key() -> ec.EllipticCurvePrivateKey:
    return ec.generate_private_key(ec.SECP256R1())


def _digest(key: PrivateKey) -> hashes.SHA256 | None:
    """Ed25519 (an operator's CA may be one) signs without a separate hash."""
    return None if isinstance(key, ed25519.Ed25519PrivateKey) else hashes.SHA256()


def _subject(common_name: str) -> x509.Name:
    return x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, common_name)])


def make_ca(common_name: str = "aesop-ca", *, days: int = 3650) -> tuple[PrivateKey, Certificate]:
    """A new self-signed CA that may sign leaves only (path length 0)."""
    if days < 1:
        raise ValueError(f"days must be at least 1, not {days}")
    key = _new_key()
    now = _now()
    name = _subject(common_name)
    ski = x509.SubjectKeyIdentifier.from_public_key(key.public_key())
    cert = (
        x509.CertificateBuilder()
        .subject_name(name).issuer_name(name)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - BACKDATE)
        .not_valid_after(now + datetime.timedelta(days=days))
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(x509.KeyUsage(
            digital_signature=True, key_cert_sign=True, crl_sign=True,
            content_commitment=False, key_encipherment=False, data_encipherment=False,
            key_agreement=False, encipher_only=False, decipher_only=False), critical=True)
        .add_extension(ski, critical=False)
        .add_extension(x509.AuthorityKeyIdentifier.from_issuer_subject_key_identifier(ski),
                       critical=False)
        .sign(key, _digest(key))
    )
    return key, cert


def _usages(server: bool) -> list[x509.ObjectIdentifier]:
    return [ExtendedKeyUsageOID.CLIENT_AUTH, *([ExtendedKeyUsageOID.SERVER_AUTH] if server
                                               else [])]


def _authority_key_id(ca_key: PrivateKey, ca_cert: Certificate) -> x509.AuthorityKeyIdentifier:
    try:
        ski = ca_cert.extensions.get_extension_for_class(x509.SubjectKeyIdentifier).value
    except x509.ExtensionNotFound:  # an operator's CA without one
        return x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key())
    return x509.AuthorityKeyIdentifier.from_issuer_subject_key_identifier(ski)


def issue(ca_key: PrivateKey, ca_cert: Certificate, common_name: str, *,
          server_names: Sequence[str] = (), days: int = 825) -> tuple[PrivateKey, Certificate]:
    """A leaf for ``common_name`` signed by the CA: clientAuth always, serverAuth too when
    ``server_names`` are given (its SAN); with none the SAN is the common name as a DNS
    name (rustls refuses some certificates without one). It ends no later than the CA."""
    if days < 1:
        raise ValueError(f"days must be at least 1, not {days}")
    key = _new_key()
    now = _now()
    end = min(now + datetime.timedelta(days=days), ca_cert.not_valid_after_utc)
    if end <= now:
        raise ValueError(f"the CA {ca_cert.subject.rfc4514_string()} has expired")
    names = list(server_names) or [common_name]
    cert = (
        x509.CertificateBuilder()
        .subject_name(_subject(common_name)).issuer_name(ca_cert.subject)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(max(now - BACKDATE, ca_cert.not_valid_before_utc))
        .not_valid_after(end)
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(x509.KeyUsage(
            digital_signature=True, key_cert_sign=False, crl_sign=False,
            content_commitment=False, key_encipherment=False, data_encipherment=False,
            key_agreement=False, encipher_only=False, decipher_only=False), critical=True)
        .add_extension(x509.ExtendedKeyUsage(_usages(bool(server_names))), critical=False)
        .add_extension(x509.SubjectAlternativeName(san_of(names)), critical=False)
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()),
                       critical=False)
        .add_extension(_authority_key_id(ca_key, ca_cert), critical=False)
        .sign(ca_key, _digest(ca_key))
    )
    return key, cert


def cert_pem(cert: Certificate) -> bytes:
    return cert.public_bytes(serialization.Encoding.PEM)


def key_pem(key: PrivateKey) -> bytes:
    return key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                             serialization.NoEncryption())


def load_key(path: Path) -> PrivateKey:
    """A PEM private key (unencrypted) of a kind that signs certificates rustls accepts."""
    try:
        key = serialization.load_pem_private_key(path.read_bytes(), password=None)
    except (TypeError, ValueError) as e:  # TypeError: it is encrypted
        raise ValueError(f"{path}: not an unencrypted PEM private key ({e})") from e
    if not isinstance(key, _SIGNERS):
        raise ValueError(f"{path}: a {type(key).__name__} cannot sign the stack's certificates"
                         " (use EC, RSA or Ed25519)")
    return key


def load_cert(path: Path) -> Certificate:
    try:
        return x509.load_pem_x509_certificate(path.read_bytes())
    except ValueError as e:
        raise ValueError(f"{path}: not a PEM certificate ({e})") from e


def common_name(cert_path: Path) -> str:
    """The common name of the certificate at ``cert_path`` (the ACL's subject)."""
    names = load_cert(cert_path).subject.get_attributes_for_oid(NameOID.COMMON_NAME)
    if not names:
        raise ValueError(f"{cert_path}: the certificate has no common name")
    value = names[0].value
    return value if isinstance(value, str) else value.decode()


def _public(key_or_cert: PrivateKey | Certificate) -> bytes:
    public = key_or_cert.public_key()
    return public.public_bytes(serialization.Encoding.PEM,
                               serialization.PublicFormat.SubjectPublicKeyInfo)


def _signed_by(cert: Certificate, ca_cert: Certificate) -> bool:
    try:
        cert.verify_directly_issued_by(ca_cert)
    except (ValueError, TypeError, InvalidSignature):
        return False
    return True


def _still_good(cert_path: Path, key_path: Path, ca_cert: Certificate, name: str,
                server_names: Sequence[str]) -> bool:
    """Whether the leaf there is what ``issue`` would make now, so it is kept: signed by
    the CA in use, its key beside it, the same name, SAN and usages, and more than
    ``RENEW_BEFORE`` left."""
    try:
        cert, key = load_cert(cert_path), load_key(key_path)
        sans = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
        usages = cert.extensions.get_extension_for_class(x509.ExtendedKeyUsage).value
        cn = common_name(cert_path)
    except (OSError, ValueError, x509.ExtensionNotFound):
        return False
    return (_signed_by(cert, ca_cert) and _public(cert) == _public(key) and cn == name
            and set(sans) == set(san_of(list(server_names) or [name]))
            and set(usages) == set(_usages(bool(server_names)))
            and cert.not_valid_after_utc - _now() > RENEW_BEFORE)


def _write_public(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` (0644) by a rename, so a reader never sees half a file,
    and only when it changed, so a kept file stays byte-identical."""
    if path.is_file() and not path.is_symlink() and path.read_bytes() == data:
        return
    write_file(path, data, 0o644)


def _keep_private(key_path: Path) -> None:
    """A kept key is 0600 too, whatever became of its mode (not through a link)."""
    if not key_path.is_symlink():
        key_path.chmod(0o600)


def _private_folder(folder: Path) -> None:
    folder.mkdir(mode=0o700, parents=True, exist_ok=True)
    folder.chmod(0o700)


def _ca_in_use(folder: Path, ca_cert: Path | None, ca_key: Path | None
               ) -> tuple[PrivateKey, Certificate]:
    """The operator's CA if given (its certificate copied in, its key never), else the
    folder's, else a new one written there."""
    if (ca_cert is None) != (ca_key is None):
        raise ValueError("give both the CA certificate and its key, or neither")
    here_cert, here_key = folder / "ca.pem", folder / "ca-key.pem"
    if ca_cert is not None and ca_key is not None:
        key, cert = load_key(ca_key), load_cert(ca_cert)
        source = f"{ca_key} and {ca_cert}"
    elif here_cert.exists() and here_key.exists():
        key, cert = load_key(here_key), load_cert(here_cert)
        _keep_private(here_key)
        source = f"{here_key} and {here_cert}"
    elif here_cert.exists():
        raise FileNotFoundError(
            f"{here_cert} exists but {here_key} does not (an operator's CA?): pass its "
            f"certificate and key to `{COMMAND}`, or remove {here_cert} to start a new CA "
            "(every certificate then has to be copied out again)")
    else:
        key, cert = make_ca()
        write_private(here_key, key_pem(key).decode())
        source = ""
    if source:
        if _public(key) != _public(cert):
            raise ValueError(f"{source} do not belong together: the key is not the CA's")
        try:
            is_ca = cert.extensions.get_extension_for_class(x509.BasicConstraints).value.ca
        except x509.ExtensionNotFound:
            is_ca = False
        if not is_ca:
            raise ValueError(f"{source}: the certificate is not a CA (basicConstraints)")
    _write_public(here_cert, cert_pem(cert))
    return key, cert


def write_certs(folder: Path, *, robots: Sequence[str], services: Sequence[str],
                server_names: Sequence[str] = (), ca_cert: Path | None = None,
                ca_key: Path | None = None, days: int = 825) -> CertLayout:
    """Lay out ``folder`` (see the module's docstring) and return where everything is.

    Names are all checked before anything is written. Each leaf there is kept unless
    another CA issued it, it expires within ``RENEW_BEFORE``, its names or usages differ
    from what is asked (the router's server names), or its key is missing: then it is
    issued again. Keys are 0600, folders 0700.
    """
    robots = [check_name(r, "robot id") for r in robots]
    services = [check_name(s, "service name") for s in services]
    for name in services:
        if name == ROUTER or name.startswith("robot-") or name in {"ca", "ca-key"}:
            raise ValueError(f"bad service name {name!r}: taken by the router, CA or robots")
    wanted = [check_server_name(n) for n in server_names]
    router_names = [e.value if isinstance(e, x509.DNSName) else str(e.value)
                    for e in san_of([*wanted, *LOCAL_NAMES])]
    _private_folder(folder)
    key, cert = _ca_in_use(folder, ca_cert, ca_key)
    layout = CertLayout(folder, tuple(dict.fromkeys(robots)), tuple(dict.fromkeys(services)))
    issued: list[str] = []

    def leaf(name: str, cert_path: Path, key_path: Path, names: Sequence[str] = ()) -> None:
        if _still_good(cert_path, key_path, cert, name, names):
            _keep_private(key_path)
            return
        leaf_key, leaf_cert = issue(key, cert, name, server_names=names, days=days)
        write_private(key_path, key_pem(leaf_key).decode())  # the key first: a cert
        _write_public(cert_path, cert_pem(leaf_cert))  # without it would be issued again
        issued.append(name)

    leaf(ROUTER, layout.router, layout.router_key, router_names)
    for service in layout.services:
        leaf(service, layout.cert(service), layout.key(service))
    for robot in layout.robots:
        _private_folder(layout.robot_folder(robot))
        _write_public(layout.robot_ca(robot), cert_pem(cert))
        leaf(robot_name(robot), layout.robot_cert(robot), layout.robot_key(robot))
    return CertLayout(layout.folder, layout.robots, layout.services, tuple(issued))


def load_identity(folder: Path, name: str) -> tuple[Path, Path, Path]:
    """The CA, certificate and key paths of subject ``name`` (``router``, a service,
    ``robot-<id>``) in ``folder``: the server's folder, a robot's folder in it, or that
    robot folder copied to the robot's computer. A missing file is named with the
    command that makes it."""
    check_name(name)
    base = folder / name if (folder / name).is_dir() else folder
    paths = (base / "ca.pem", base / f"{name}.pem", base / f"{name}-key.pem")
    for path in paths:
        if not path.is_file():
            if name.startswith("robot-"):
                make = (f"`{COMMAND} DIR --robot {name.removeprefix('robot-')}` on the "
                        f"server, then copy DIR/{name}/ here")
            elif name == ROUTER:
                make = f"`{COMMAND} {folder} --server-name <this server's name>`"
            else:
                make = f"`{COMMAND} {folder}`"
            raise FileNotFoundError(f"{path} is missing: make it with {make}")
    return paths


def tls_link(folder: Path, name: str, *, listen: bool) -> dict[str, object]:
    """The ``transport/link/tls`` config block of subject ``name``'s session: mutual TLS
    with its certificate, as the router (``listen``) or as a client connecting to it."""
    ca, cert, key = load_identity(folder, name)
    side = "listen" if listen else "connect"
    return {"root_ca_certificate": str(ca), f"{side}_certificate": str(cert),
            f"{side}_private_key": str(key), "enable_mtls": True}
