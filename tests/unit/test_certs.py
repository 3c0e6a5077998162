"""The stack's certificate authority (tools/stack/certs.py): the layout, what each
certificate says, re-runs that keep what was issued, an operator's CA, and real Zenoh
sessions over mutual TLS with them (and an ACL naming a robot by its certificate)."""

from __future__ import annotations

import datetime
import ipaddress
import json
import re
import stat
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
import zenoh
from cryptography import x509
from cryptography.hazmat.primitives import hashes
from cryptography.hazmat.primitives.asymmetric import ec, ed25519, rsa
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from shared.process import free_port
from tools.stack import certs
from tools.stack.acl import write_private
from tools.stack.certs import ROUTER, CertLayout, write_certs

ROBOTS = ("robot0", "robot1")
SERVICES = ("embedding", "reasoner", "dashboard", "monitor")
SERVER_NAMES = ("server.lan", "10.0.0.5")
CLIENT, SERVER = ExtendedKeyUsageOID.CLIENT_AUTH, ExtendedKeyUsageOID.SERVER_AUTH


def load(path: Path) -> x509.Certificate:
    return x509.load_pem_x509_certificate(path.read_bytes())


def cn(cert: x509.Certificate) -> str:
    return str(cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)[0].value)


def sans(cert: x509.Certificate) -> tuple[set[str], set[str]]:
    """The DNS names and the IP addresses of the certificate's subjectAltName."""
    san = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    return (set(san.get_values_for_type(x509.DNSName)),
            {str(ip) for ip in san.get_values_for_type(x509.IPAddress)})


def usages(cert: x509.Certificate) -> set[x509.ObjectIdentifier]:
    return set(cert.extensions.get_extension_for_class(x509.ExtendedKeyUsage).value)


def mode(path: Path) -> int:
    return stat.S_IMODE(path.stat().st_mode)


def leaves(layout: CertLayout) -> dict[str, tuple[Path, Path]]:
    """Every leaf's (certificate, key) by its common name."""
    out = {name: (layout.cert(name), layout.key(name)) for name in (ROUTER, *layout.services)}
    for robot in layout.robots:
        out[f"robot-{robot}"] = (layout.robot_cert(robot), layout.robot_key(robot))
    return out


def snapshot(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes()
            for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def layout(tmp_path_factory: pytest.TempPathFactory) -> CertLayout:
    return write_certs(tmp_path_factory.mktemp("certs") / "zenoh", robots=ROBOTS,
                       services=SERVICES, server_names=SERVER_NAMES)


def test_the_layout_and_its_modes(layout: CertLayout) -> None:
    top = {"ca.pem", "ca-key.pem", "router.pem", "router-key.pem",
           *(f"{s}{end}" for s in SERVICES for end in (".pem", "-key.pem")),
           *(f"robot-{r}" for r in ROBOTS)}
    assert {p.name for p in layout.folder.iterdir()} == top
    for robot in ROBOTS:
        folder = layout.robot_folder(robot)
        assert folder == layout.folder / f"robot-{robot}"
        assert {p.name for p in folder.iterdir()} == {
            "ca.pem", f"robot-{robot}.pem", f"robot-{robot}-key.pem"}
        assert mode(folder) == 0o700
        assert layout.robot_ca(robot).read_bytes() == layout.ca.read_bytes()
    assert mode(layout.folder) == 0o700
    keys = [p for p in layout.folder.rglob("*key.pem")]
    assert len(keys) == 1 + 1 + len(SERVICES) + len(ROBOTS)
    assert all(mode(key) == 0o600 for key in keys)
    assert layout.issued == (ROUTER, *SERVICES, *(f"robot-{r}" for r in ROBOTS))


def test_each_certificate_says_who_it_is_and_what_it_may_do(layout: CertLayout) -> None:
    ca = load(layout.ca)
    assert ca.version == x509.Version.v3 and cn(ca) == "aesop-ca"
    assert ca.extensions.get_extension_for_class(x509.BasicConstraints).value.ca
    for name, (cert_path, key_path) in leaves(layout).items():
        cert = load(cert_path)
        assert cn(cert) == name == certs.common_name(cert_path)
        assert cert.version == x509.Version.v3
        assert not cert.extensions.get_extension_for_class(x509.BasicConstraints).value.ca
        assert cert.extensions.get_extension_for_class(x509.KeyUsage).value.digital_signature
        assert isinstance(cert.public_key(), ec.EllipticCurvePublicKey)
        assert cert.public_key().curve.name == "secp256r1"  # type: ignore[union-attr]
        assert b"BEGIN PRIVATE KEY" in key_path.read_bytes()  # PKCS8
        ski = cert.extensions.get_extension_for_class(x509.SubjectKeyIdentifier).value
        aki = cert.extensions.get_extension_for_class(x509.AuthorityKeyIdentifier).value
        ca_ski = ca.extensions.get_extension_for_class(x509.SubjectKeyIdentifier).value
        assert ski.digest != ca_ski.digest and aki.key_identifier == ca_ski.digest
        if name == ROUTER:
            assert usages(cert) == {CLIENT, SERVER}
            assert sans(cert) == ({"server.lan", "localhost"}, {"10.0.0.5", "127.0.0.1", "::1"})
        else:
            assert usages(cert) == {CLIENT}
            assert sans(cert) == ({name}, set())


def test_every_leaf_is_signed_by_the_ca(layout: CertLayout) -> None:
    ca = load(layout.ca)
    for cert_path, _ in leaves(layout).values():
        cert = load(cert_path)
        cert.verify_directly_issued_by(ca)  # the issuer's name and the signature
        assert cert.not_valid_after_utc <= ca.not_valid_after_utc
    other_key, other = certs.make_ca("someone-else")
    with pytest.raises(ValueError):
        load(layout.router).verify_directly_issued_by(other)


def test_issue_writes_ip_addresses_as_such() -> None:
    ca_key, ca = certs.make_ca()
    _, cert = certs.issue(ca_key, ca, "x", server_names=["fe80::1", "a.b", "192.168.1.2"])
    assert sans(cert) == ({"a.b"}, {"fe80::1", "192.168.1.2"})
    san = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert ipaddress.ip_address("192.168.1.2") in san.get_values_for_type(x509.IPAddress)


def test_a_second_run_keeps_everything_and_adds_a_robot(tmp_path: Path) -> None:
    folder = tmp_path / "zenoh"
    write_certs(folder, robots=["robot0"], services=["embedding"], server_names=SERVER_NAMES)
    (folder / "ca-key.pem").chmod(0o644)
    (folder / "robot-robot0" / "robot-robot0-key.pem").chmod(0o640)
    before = snapshot(folder)
    again = write_certs(folder, robots=["robot0"], services=["embedding"],
                        server_names=SERVER_NAMES)
    assert again.issued == () and snapshot(folder) == before
    assert {mode(key) for key in folder.rglob("*key.pem")} == {0o600}  # kept, and private
    more = write_certs(folder, robots=["robot0", "robot7"], services=["embedding"],
                       server_names=SERVER_NAMES)
    assert more.issued == ("robot-robot7",)
    after = snapshot(folder)
    assert {k: v for k, v in after.items() if k in before} == before
    load(more.robot_cert("robot7")).verify_directly_issued_by(load(folder / "ca.pem"))


def test_the_router_is_issued_again_when_its_names_change(tmp_path: Path) -> None:
    folder = tmp_path / "zenoh"
    write_certs(folder, robots=["robot0"], services=[], server_names=["server.lan"])
    robot = snapshot(folder / "robot-robot0")
    layout = write_certs(folder, robots=["robot0"], services=[],
                         server_names=["server.lan", "10.0.0.9"])
    assert layout.issued == (ROUTER,)
    assert "10.0.0.9" in sans(load(layout.router))[1]
    assert snapshot(folder / "robot-robot0") == robot


def test_an_expiring_or_foreign_or_keyless_leaf_is_issued_again(tmp_path: Path) -> None:
    folder = tmp_path / "zenoh"
    layout = write_certs(folder, robots=["robot0", "robot1"], services=["embedding"])
    ca_key = certs.load_key(layout.ca_key)
    _, soon = certs.issue(ca_key, load(layout.ca), "robot-robot0", days=10)  # < 30 days left
    layout.robot_cert("robot0").write_bytes(certs.cert_pem(soon))
    other_key, other = certs.make_ca("someone-else")
    key, foreign = certs.issue(other_key, other, "embedding")
    layout.cert("embedding").write_bytes(certs.cert_pem(foreign))
    write_private(layout.key("embedding"), certs.key_pem(key).decode())
    layout.robot_key("robot1").unlink()
    again = write_certs(folder, robots=["robot0", "robot1"], services=["embedding"])
    assert set(again.issued) == {"robot-robot0", "robot-robot1", "embedding"}
    ca = load(layout.ca)
    for cert_path, key_path in leaves(again).values():
        load(cert_path).verify_directly_issued_by(ca)
        assert mode(key_path) == 0o600
    left = load(again.robot_cert("robot0")).not_valid_after_utc - datetime.datetime.now(
        datetime.UTC)
    assert left > datetime.timedelta(days=800)


def test_an_operators_ca_is_used_and_its_key_never_copied(tmp_path: Path) -> None:
    ca_key, ca = certs.make_ca("operator-ca")
    ca_cert_path, ca_key_path = tmp_path / "op.pem", tmp_path / "op-key.pem"
    ca_cert_path.write_bytes(certs.cert_pem(ca))
    write_private(ca_key_path, certs.key_pem(ca_key).decode())
    folder = tmp_path / "zenoh"
    layout = write_certs(folder, robots=["robot0"], services=["embedding"],
                         ca_cert=ca_cert_path, ca_key=ca_key_path)
    assert layout.ca.read_bytes() == ca_cert_path.read_bytes()
    assert layout.robot_ca("robot0").read_bytes() == ca_cert_path.read_bytes()
    assert not layout.ca_key.exists()
    key_bytes = ca_key_path.read_bytes()
    assert all(p.read_bytes() != key_bytes for p in folder.rglob("*") if p.is_file())
    for cert_path, _ in leaves(layout).values():
        load(cert_path).verify_directly_issued_by(ca)
    # the folder's CA has no key: without the operator's, nothing can be issued
    with pytest.raises(FileNotFoundError, match="ca-key.pem"):
        write_certs(folder, robots=["robot0", "robot1"], services=[])
    with pytest.raises(ValueError, match="both"):
        write_certs(folder, robots=[], services=[], ca_cert=ca_cert_path)
    _, other = certs.make_ca("other")
    ca_cert_path.write_bytes(certs.cert_pem(other))  # a key and a CA that do not match
    with pytest.raises(ValueError, match="belong together"):
        write_certs(folder, robots=[], services=[], ca_cert=ca_cert_path, ca_key=ca_key_path)


def operator_ca(key: certs.PrivateKey) -> x509.Certificate:
    """An operator's CA made elsewhere: no key identifiers, any key rustls accepts."""
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "operator")])
    now = datetime.datetime.now(datetime.UTC)
    digest = None if isinstance(key, ed25519.Ed25519PrivateKey) else hashes.SHA256()
    return (x509.CertificateBuilder().subject_name(name).issuer_name(name)
            .public_key(key.public_key()).serial_number(x509.random_serial_number())
            .not_valid_before(now).not_valid_after(now + datetime.timedelta(days=400))
            .add_extension(x509.BasicConstraints(ca=True, path_length=None), critical=True)
            .sign(key, digest))


@pytest.mark.parametrize("make_key", [
    lambda: rsa.generate_private_key(public_exponent=65537, key_size=2048),
    ed25519.Ed25519PrivateKey.generate,
], ids=["rsa", "ed25519"])
def test_an_operators_rsa_or_ed25519_ca_issues_too(
        tmp_path: Path, make_key: Callable[[], certs.PrivateKey]) -> None:
    key = make_key()
    ca = operator_ca(key)
    (tmp_path / "op.pem").write_bytes(certs.cert_pem(ca))
    write_private(tmp_path / "op-key.pem", certs.key_pem(key).decode())
    layout = write_certs(tmp_path / "zenoh", robots=["robot0"], services=[],
                         ca_cert=tmp_path / "op.pem", ca_key=tmp_path / "op-key.pem")
    for cert_path, _ in leaves(layout).values():
        cert = load(cert_path)
        cert.verify_directly_issued_by(ca)
        assert cert.not_valid_after_utc <= ca.not_valid_after_utc  # no later than the CA
        assert cert.extensions.get_extension_for_class(x509.AuthorityKeyIdentifier)


def test_a_leaf_as_the_ca_is_refused(tmp_path: Path, layout: CertLayout) -> None:
    with pytest.raises(ValueError, match="not a CA"):
        write_certs(tmp_path / "zenoh", robots=[], services=[], ca_cert=layout.router,
                    ca_key=layout.router_key)


@pytest.mark.parametrize(("kwargs", "bad"), [
    ({"robots": ["robot0", "../etc"]}, "../etc"),
    ({"robots": ["robot 1"]}, "robot 1"),
    ({"robots": [""]}, ""),
    ({"services": ["emb/edding"]}, "emb/edding"),
    ({"services": ["robot-robot0"]}, "robot-robot0"),
    ({"services": [ROUTER]}, ROUTER),
    ({"server_names": ["server..lan"]}, "server..lan"),
    ({"server_names": ["-bad.lan"]}, "-bad.lan"),
    ({"server_names": ["10.0.0.256"]}, "10.0.0.256"),
    ({"server_names": ["host name"]}, "host name"),
])
def test_a_bad_name_is_refused_by_its_value(tmp_path: Path, kwargs: dict[str, Any],
                                            bad: str) -> None:
    args: dict[str, Any] = {"robots": [], "services": [], **kwargs}
    with pytest.raises(ValueError, match=re.escape(repr(bad))):
        write_certs(tmp_path / "zenoh", **args)
    assert not (tmp_path / "zenoh").exists()  # checked before anything is written


def test_server_names_accept_dns_names_and_ip_addresses() -> None:
    for name in ("server.lan", "localhost", "*.fleet.example", "10.0.0.5", "::1", "Server.LAN."):
        certs.check_server_name(name)
    assert certs.check_server_name("Server.LAN.") == "server.lan"


def test_load_identity_finds_a_subject_or_says_how_to_make_it(layout: CertLayout) -> None:
    assert certs.load_identity(layout.folder, ROUTER) == (
        layout.ca, layout.router, layout.router_key)
    robot = (layout.robot_ca("robot0"), layout.robot_cert("robot0"), layout.robot_key("robot0"))
    assert certs.load_identity(layout.folder, "robot-robot0") == robot
    assert certs.load_identity(layout.robot_folder("robot0"), "robot-robot0") == robot
    with pytest.raises(FileNotFoundError, match=r"robot-robot9\.pem.*aesop zenoh certs "
                                                r"DIR --robot robot9"):
        certs.load_identity(layout.folder, "robot-robot9")
    with pytest.raises(FileNotFoundError, match=r"control\.pem.*aesop zenoh certs"):
        certs.load_identity(layout.folder, "control")


# -- real Zenoh over mutual TLS ------------------------------------------------------------

def config(mode: str, endpoints: dict[str, list[str]], tls: dict[str, object],
           acl: dict[str, Any] | None = None) -> zenoh.Config:
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps(mode))
    for side, eps in endpoints.items():
        conf.insert_json5(f"{side}/endpoints", json.dumps(eps))
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("transport/link/tls", json.dumps(tls))
    if acl is not None:
        conf.insert_json5("access_control", json.dumps(acl))
    return conf


def client_tls(ca: Path, cert: Path, key: Path) -> dict[str, object]:
    return {"root_ca_certificate": str(ca), "connect_certificate": str(cert),
            "connect_private_key": str(key), "enable_mtls": True}


class Router:
    """A router session listening on TLS with router.pem, and what it hears on aesop/**."""

    def __init__(self, layout: CertLayout, acl: dict[str, Any] | None = None) -> None:
        self.endpoint = f"tls/127.0.0.1:{free_port()}"
        self.session = zenoh.open(config("router", {"listen": [self.endpoint]},
                                         certs.tls_link(layout.folder, ROUTER, listen=True),
                                         acl))
        self.keys: list[str] = []
        self._lock = threading.Lock()
        self._sub = self.session.declare_subscriber("aesop/**", self._on)

    def _on(self, sample: zenoh.Sample) -> None:
        with self._lock:
            self.keys.append(str(sample.key_expr))

    def heard(self) -> list[str]:
        with self._lock:
            return list(self.keys)

    def client(self, ca: Path, cert: Path, key: Path) -> zenoh.Session:
        return zenoh.open(config("client", {"connect": [self.endpoint]},
                                 client_tls(ca, cert, key)))


@pytest.fixture
def router(layout: CertLayout, request: pytest.FixtureRequest) -> Iterator[Router]:
    router = Router(layout, getattr(request, "param", None))
    yield router
    router.session.close()


def routed(put: Callable[[], None], router: Router, key: str) -> None:
    """Put until the router hears ``key`` (the routes settle), then a moment more."""
    deadline = time.monotonic() + 20
    while key not in router.heard():
        assert time.monotonic() < deadline, f"{key} never reached the router"
        put()
        time.sleep(0.1)
    time.sleep(0.3)


def robot_identity(layout: CertLayout, robot: str) -> tuple[Path, Path, Path]:
    return certs.load_identity(layout.robot_folder(robot), f"robot-{robot}")


@pytest.mark.timeout(60)
def test_a_robot_with_its_folder_puts_through_the_router(layout: CertLayout,
                                                         router: Router) -> None:
    with router.client(*robot_identity(layout, "robot0")) as robot:
        routed(lambda: robot.put("aesop/robot0/x", b"hello"), router, "aesop/robot0/x")


@pytest.mark.timeout(60)
def test_a_client_with_a_certificate_of_another_ca_is_refused(layout: CertLayout,
                                                              router: Router,
                                                              tmp_path: Path) -> None:
    other = write_certs(tmp_path / "other", robots=["robot0"], services=[])
    # it trusts the right CA, so only the router's check of its certificate refuses it
    with pytest.raises(zenoh.ZError):
        router.client(layout.ca, other.robot_cert("robot0"), other.robot_key("robot0"))
    with pytest.raises(zenoh.ZError):  # and the other CA's whole folder
        router.client(*robot_identity(other, "robot0"))
    with router.client(*robot_identity(layout, "robot1")):  # the router still serves
        pass


ROBOT0_ONLY = {
    "enabled": True,
    "default_permission": "deny",
    "rules": [
        {"id": "robot0-puts", "permission": "allow", "flows": ["ingress"],
         "messages": ["put"], "key_exprs": ["aesop/robot0/**"]},
        # the router's subscriber must be declared to the client, or it puts nothing
        {"id": "subscribers", "permission": "allow", "flows": ["egress"],
         "messages": ["declare_subscriber"], "key_exprs": ["aesop/**"]},
    ],
    "subjects": [{"id": "robot-robot0", "cert_common_names": ["robot-robot0"]}],
    "policies": [{"id": "robot0", "rules": ["robot0-puts", "subscribers"],
                  "subjects": ["robot-robot0"]}],
}


@pytest.mark.timeout(60)
@pytest.mark.parametrize("router", [ROBOT0_ONLY], indirect=True)
def test_the_acl_knows_a_robot_by_its_certificates_common_name(layout: CertLayout,
                                                               router: Router) -> None:
    with router.client(*robot_identity(layout, "robot0")) as robot0, \
            router.client(*robot_identity(layout, "robot1")) as robot1:
        routed(lambda: robot0.put("aesop/robot0/x", b"own"), router, "aesop/robot0/x")
        robot0.put("aesop/robot1/x", b"forged")
        robot1.put("aesop/robot1/y", b"no rule for robot-robot1")
        robot0.put("aesop/robot0/z", b"own, after")
        routed(lambda: robot0.put("aesop/robot0/z", b"own, after"), router, "aesop/robot0/z")
    assert set(router.heard()) == {"aesop/robot0/x", "aesop/robot0/z"}
