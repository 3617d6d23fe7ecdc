"""Deployment security: the certificates of a deployment, the secure router configurations, the loopback rule.

`aermani certs init` makes a private CA and one certificate per identity (distinct common names, which the
routers' access control keys on). `router_config` loads a router template from `shared/routers/` (the same
file docker compose mounts) and only rewrites certificate paths and endpoints, so the access control that
runs in tests, in `aermani up --secure` and in compose is one text. Without TLS, a router may only listen
on loopback (`require_loopback`).
"""

from __future__ import annotations

import datetime as dt
import ipaddress
import json
import os
from dataclasses import dataclass
from pathlib import Path

import zenoh

from shared.errors import ConfigError

ROUTERS_DIR = Path(__file__).resolve().parent / "routers"
ROLES = ("ground", "drone")
# Identity -> certificate common name. The routers' access control (shared/routers/*.json5) names these.
IDENTITIES = {"ground": "aermani-ground", "drone": "aermani-drone", "client": "aermani-client"}
CA_NAME = "aermani deployment CA"
DEFAULT_LOCAL_PORT = 7447
DEFAULT_TLS_PORT = 7448


@dataclass(frozen=True)
class CertFiles:
    """Paths of one identity's files inside a certificate directory."""

    ca: Path
    cert: Path
    key: Path


def cert_files(certs_dir: str | Path, identity: str) -> CertFiles:
    if identity not in IDENTITIES:
        raise ConfigError(f"unknown identity {identity!r}: use one of {sorted(IDENTITIES)}")
    d = Path(certs_dir)
    return CertFiles(d / "ca.pem", d / f"{identity}.pem", d / f"{identity}.key")


def check_cert_files(certs_dir: str | Path, identity: str) -> CertFiles:
    """The files, or a ConfigError naming the missing ones and how to make them."""
    files = cert_files(certs_dir, identity)
    missing = [str(p) for p in (files.ca, files.cert, files.key) if not p.is_file()]
    if missing:
        raise ConfigError(f"missing certificate files {missing}: run `aermani certs init --out {certs_dir}` "
                          "(or copy the deployment's files there)")
    return files


# --------------------------------------------------------------------------- certificates


def init_certs(out_dir: str | Path, *, sans: list[str] | tuple[str, ...] = (), days: int = 825,
               force: bool = False, ca_from: str | Path | None = None) -> dict[str, CertFiles]:
    """Create a CA (or reuse the one in `ca_from`) and a certificate per identity in `out_dir`.

    Each leaf carries its identity's CN, both TLS usages (a router is client and server), and subject
    alternative names localhost, 127.0.0.1, ::1, zenoh-ground, zenoh-drone plus `sans`. Private keys are
    written mode 0600. Refuses to overwrite existing files unless `force`."""
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    targets = [out / "ca.pem", *(out / f"{i}.{ext}" for i in IDENTITIES for ext in ("pem", "key"))]
    existing = [str(p) for p in targets if p.exists()]
    if existing and not force:
        raise ConfigError(f"{out} already holds {existing}; pass --force to replace them (every router and "
                          "client of the deployment then needs the new files)")
    now = dt.datetime.now(dt.UTC)
    not_before = now - dt.timedelta(minutes=5)
    pem = serialization.Encoding.PEM

    def write_key(path: Path, key: ec.EllipticCurvePrivateKey) -> None:
        data = key.private_bytes(pem, serialization.PrivateFormat.PKCS8, serialization.NoEncryption())
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.chmod(path, 0o600)

    if ca_from is not None:
        ca_dir = Path(ca_from)
        ca_cert = x509.load_pem_x509_certificate((ca_dir / "ca.pem").read_bytes())
        loaded = serialization.load_pem_private_key((ca_dir / "ca.key").read_bytes(), None)
        if not isinstance(loaded, ec.EllipticCurvePrivateKey):
            raise ConfigError(f"{ca_dir / 'ca.key'} is not an EC private key made by `aermani certs init`")
        ca_key = loaded
    else:
        ca_key = ec.generate_private_key(ec.SECP256R1())
        ca_subject = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, CA_NAME)])
        ca_cert = (
            x509.CertificateBuilder().subject_name(ca_subject).issuer_name(ca_subject)
            .public_key(ca_key.public_key()).serial_number(x509.random_serial_number())
            .not_valid_before(not_before).not_valid_after(now + dt.timedelta(days=days))
            .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
            .add_extension(x509.KeyUsage(digital_signature=False, content_commitment=False, key_encipherment=False,
                                         data_encipherment=False, key_agreement=False, key_cert_sign=True,
                                         crl_sign=True, encipher_only=False, decipher_only=False), critical=True)
            .add_extension(x509.SubjectKeyIdentifier.from_public_key(ca_key.public_key()), critical=False)
            .sign(ca_key, hashes.SHA256())
        )
        write_key(out / "ca.key", ca_key)
    (out / "ca.pem").write_bytes(ca_cert.public_bytes(pem))

    names: list[x509.GeneralName] = []
    for san in ["localhost", "127.0.0.1", "::1", "zenoh-ground", "zenoh-drone", *sans]:
        try:
            names.append(x509.IPAddress(ipaddress.ip_address(san)))
        except ValueError:
            names.append(x509.DNSName(san))
    result = {}
    for identity, cn in IDENTITIES.items():
        key = ec.generate_private_key(ec.SECP256R1())
        cert = (
            x509.CertificateBuilder()
            .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, cn)]))
            .issuer_name(ca_cert.subject).public_key(key.public_key())
            .serial_number(x509.random_serial_number())
            .not_valid_before(not_before).not_valid_after(now + dt.timedelta(days=days))
            .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
            .add_extension(x509.KeyUsage(digital_signature=True, content_commitment=False, key_encipherment=False,
                                         data_encipherment=False, key_agreement=True, key_cert_sign=False,
                                         crl_sign=False, encipher_only=False, decipher_only=False), critical=True)
            .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]),
                           critical=False)
            .add_extension(x509.SubjectAlternativeName(names), critical=False)
            .add_extension(x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()), critical=False)
            .sign(ca_key, hashes.SHA256())
        )
        files = cert_files(out, identity)
        files.cert.write_bytes(cert.public_bytes(pem))
        write_key(files.key, key)
        result[identity] = files
    return result


def common_name(cert_path: str | Path) -> str:
    from cryptography import x509
    from cryptography.x509.oid import NameOID

    cert = x509.load_pem_x509_certificate(Path(cert_path).read_bytes())
    return str(cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)[0].value)


# --------------------------------------------------------------------------- loopback rule


def is_loopback_host(host: str) -> bool:
    host = host.strip("[]")
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def endpoint_host(endpoint: str) -> tuple[str, str]:
    """`tcp/127.0.0.1:7447` -> ("tcp", "127.0.0.1"); `tls/[::1]:7448#...` -> ("tls", "::1")."""
    proto, _, rest = endpoint.partition("/")
    rest = rest.split("#", 1)[0].split("?", 1)[0]
    host = rest.rsplit(":", 1)[0] if ":" in rest else rest
    return proto, host.strip("[]")


def require_loopback(endpoints: list[str] | tuple[str, ...], what: str = "an insecure router") -> None:
    """Refuse listen endpoints that are not on loopback: without TLS and access control, anyone who reaches
    the router can command the vehicle."""
    bad = [e for e in endpoints if not is_loopback_host(endpoint_host(e)[1])]
    if bad:
        raise ConfigError(f"{what} may only listen on loopback, not {bad}: use 127.0.0.1, or run with "
                          "--secure (mutual TLS and access control; `aermani certs init` makes the certificates)")


# --------------------------------------------------------------------------- zenoh configs


def router_config(role: str, certs_dir: str | Path, *, local: str | None = None, tls_listen: list[str] | None = None,
                  connect: list[str] | None = None) -> zenoh.Config:
    """The secure router config for `role` (ground or drone) from its template, with this deployment's
    certificates and endpoints. `local` is the plain loopback endpoint for the host's own services (must be
    loopback); `tls_listen` the mutual-TLS listeners (None keeps the template's); `connect` the routers to
    link to (the drone's ground router, tls/...)."""
    if role not in ROLES:
        raise ConfigError(f"unknown router role {role!r}: use ground or drone")
    files = check_cert_files(certs_dir, role)
    cfg = zenoh.Config.from_file(str(ROUTERS_DIR / f"{role}.json5"))
    tls = {"root_ca_certificate": files.ca, "listen_certificate": files.cert, "listen_private_key": files.key,
           "connect_certificate": files.cert, "connect_private_key": files.key}
    for field, path in tls.items():
        cfg.insert_json5(f"transport/link/tls/{field}", json.dumps(str(Path(path).resolve())))
    listen = json.loads(cfg.get_json("listen/endpoints"))
    if isinstance(listen, dict):  # per-mode form
        listen = listen.get("router", [])
    local_eps = [e for e in listen if not e.startswith("tls/")]
    tls_eps = [e for e in listen if e.startswith("tls/")]
    if local is not None:
        local_eps = [local]
    if tls_listen is not None:
        tls_eps = list(tls_listen)
    require_loopback(local_eps, f"the {role} router's plain listener")
    plain = [e for e in tls_eps if not e.startswith("tls/")]
    if plain:
        raise ConfigError(f"non-TLS endpoints {plain} given as TLS listeners")
    cfg.insert_json5("listen/endpoints", json.dumps(local_eps + tls_eps))
    if connect is not None:
        not_tls = [e for e in connect if not e.startswith("tls/") and not is_loopback_host(endpoint_host(e)[1])]
        if not_tls:
            raise ConfigError(f"links leaving the host must use tls/: {not_tls}")
        cfg.insert_json5("connect/endpoints", json.dumps(list(connect)))
    return cfg


def client_config(certs_dir: str | Path, identity: str, connect: list[str], *,
                  connect_timeout_s: float | None = None) -> zenoh.Config:
    """A client session that authenticates with `identity`'s certificate over mutual TLS."""
    files = check_cert_files(certs_dir, identity)
    cfg = zenoh.Config()
    cfg.insert_json5("mode", '"client"')
    cfg.insert_json5("scouting/multicast/enabled", "false")
    cfg.insert_json5("connect/endpoints", json.dumps(list(connect)))
    timeout_ms = -1 if connect_timeout_s is None else int(connect_timeout_s * 1000)
    cfg.insert_json5("connect/timeout_ms", json.dumps(timeout_ms))
    paths = {"root_ca_certificate": files.ca, "connect_certificate": files.cert, "connect_private_key": files.key}
    for field, path in paths.items():
        cfg.insert_json5(f"transport/link/tls/{field}", json.dumps(str(path.resolve())))
    cfg.insert_json5("transport/link/tls/enable_mtls", "true")
    cfg.insert_json5("transport/link/tls/verify_name_on_connect", "false")
    return cfg
