"""Deployment security: the certificates of a deployment, the secure router configurations, the loopback rule.

`aermani certs init` makes a private CA and one certificate per identity (distinct common names, which the
routers' access control keys on). `router_config` loads a router template from `shared/routers/` (the same
file docker compose mounts) and only rewrites certificate paths and endpoints, so the access control that
runs in tests, in `aermani up --secure` and in compose is one text. Without TLS, a router may only listen
on loopback (`require_loopback`).

`aermani up --secure` goes further (`issue_service_certs`, `service_access_control`): every service gets a
certificate of its own, `<service>@<vehicle>`, signed on this machine for this run, and reaches its router
over mutual TLS on loopback; no plain listener remains. The routers' access control then names each service:
it may publish what the key declarations (`shared.keys`) say it publishes, for its own vehicle only, serve
what they say it serves, and ask only the queries in `SERVICE_ASKS`.
"""

from __future__ import annotations

import datetime as dt
import ipaddress
import json
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import zenoh

from shared.errors import ConfigError

ROUTERS_DIR = Path(__file__).resolve().parent / "routers"
ROLES = ("ground", "drone")
# Identity -> certificate common name. The routers' access control (shared/routers/*.json5) names these.
IDENTITIES = {"ground": "aermani-ground", "drone": "aermani-drone", "client": "aermani-client"}
CA_NAME = "aermani deployment CA"
# A service's own identity in `aermani up --secure`: `<service>@<vehicle>`, or `<service>@fleet` for a ground
# service serving every vehicle (gateway, recorder). Its certificate's CN is SERVICE_CN_PREFIX + identity.
SERVICE_IDENTITY = re.compile(r"(?P<service>[a-z][a-z0-9_]{0,31})@(?P<vehicle>[A-Za-z0-9_-]{1,32})")
SERVICE_CN_PREFIX = "aermani-service "
FLEET_SCOPE = "fleet"
ROUTER = "router"  # a vehicle router's own identity is ROUTER@<vehicle>
DEFAULT_LOCAL_PORT = 7447
DEFAULT_TLS_PORT = 7448


@dataclass(frozen=True)
class CertFiles:
    """Paths of one identity's files inside a certificate directory."""

    ca: Path
    cert: Path
    key: Path


def cert_files(certs_dir: str | Path, identity: str) -> CertFiles:
    if identity not in IDENTITIES and not SERVICE_IDENTITY.fullmatch(identity):
        raise ConfigError(f"unknown identity {identity!r}: use one of {sorted(IDENTITIES)} (or a service's own, "
                          "<service>@<vehicle>, which `aermani up --secure` issues)")
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
    from cryptography.x509.oid import NameOID

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
        _write_key(path, key.private_bytes(pem, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()))

    if ca_from is not None:
        ca_cert, ca_key = load_ca(ca_from)
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

    result = {}
    for identity, cn in IDENTITIES.items():
        files = cert_files(out, identity)
        _write_leaf(files, cn, ca_cert, ca_key, sans=sans, days=days)
        result[identity] = files
    return result


def _write_leaf(files: CertFiles, cn: str, ca_cert: Any, ca_key: Any, *, sans: list[str] | tuple[str, ...] = (),
                days: int = 825) -> None:
    """One leaf certificate for `cn` signed by the CA, and its private key (mode 0600). Each leaf carries both
    TLS usages (a router is client and server) and the loopback and compose names plus `sans`."""
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

    now = dt.datetime.now(dt.UTC)
    names: list[x509.GeneralName] = []
    for san in ["localhost", "127.0.0.1", "::1", "zenoh-ground", "zenoh-drone", *sans]:
        try:
            names.append(x509.IPAddress(ipaddress.ip_address(san)))
        except ValueError:
            names.append(x509.DNSName(san))
    key = ec.generate_private_key(ec.SECP256R1())
    cert = (
        x509.CertificateBuilder()
        .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, cn)]))
        .issuer_name(ca_cert.subject).public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - dt.timedelta(minutes=5)).not_valid_after(now + dt.timedelta(days=days))
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
    files.cert.write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    _write_key(files.key, key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                                            serialization.NoEncryption()))


def _write_key(path: Path, data: bytes) -> None:
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "wb") as f:
        f.write(data)
    os.chmod(path, 0o600)


def load_ca(certs_dir: str | Path) -> tuple[Any, Any]:
    """The deployment CA's certificate and private key from `certs_dir`, or a ConfigError saying what is
    missing: only the machine that holds ca.key can sign (`aermani certs init --ca-from`, and `aermani up
    --secure`, which signs each service's own certificate)."""
    from cryptography import x509
    from cryptography.hazmat.primitives import serialization
    from cryptography.hazmat.primitives.asymmetric import ec

    d = Path(certs_dir)
    key_path = d / "ca.key"
    if not key_path.is_file():
        raise ConfigError(f"{key_path} is missing: signing a certificate (a new identity, or each service's own "
                          "in `aermani up --secure`) needs the deployment CA's key, on the machine that signs")
    ca_cert = x509.load_pem_x509_certificate((d / "ca.pem").read_bytes())
    ca_key = serialization.load_pem_private_key(key_path.read_bytes(), None)
    if not isinstance(ca_key, ec.EllipticCurvePrivateKey):
        raise ConfigError(f"{key_path} is not an EC private key made by `aermani certs init`")
    return ca_cert, ca_key


def service_identity(service: str, vehicle_id: str | None) -> str:
    """`executor@am1`; `gateway@fleet` for a ground service that serves every vehicle (vehicle_id None)."""
    identity = f"{service}@{vehicle_id or FLEET_SCOPE}"
    if not SERVICE_IDENTITY.fullmatch(identity):
        raise ConfigError(f"no service identity can be made for service {service!r} on vehicle {vehicle_id!r}")
    return identity


def issue_service_certs(certs_dir: str | Path, out_dir: str | Path, identities: list[str], *,
                        days: int = 2) -> None:
    """Sign a certificate for each service identity with the deployment's CA in `certs_dir` (this machine
    holds ca.key: it is the one that signs) into `out_dir`, beside a copy of ca.pem. `out_dir` is made
    private (0700); the leaves live `days` days: they are issued again at every start."""
    from cryptography.hazmat.primitives import serialization

    ca_cert, ca_key = load_ca(certs_dir)
    out = Path(out_dir)
    out.mkdir(mode=0o700, parents=True, exist_ok=True)
    os.chmod(out, 0o700)
    (out / "ca.pem").write_bytes(ca_cert.public_bytes(serialization.Encoding.PEM))
    for identity in identities:
        if not SERVICE_IDENTITY.fullmatch(identity):
            raise ConfigError(f"{identity!r} is not a service identity (<service>@<vehicle>)")
        _write_leaf(cert_files(out, identity), SERVICE_CN_PREFIX + identity, ca_cert, ca_key, days=days)


# --------------------------------------------------------------------------- per-service access control

# The queries each service sends. The key declarations say who serves a query, not who asks it; a service
# missing here may ask nothing (a query it sends anyway is refused by its router, as an outsider's is).
SERVICE_ASKS: dict[str, tuple[str, ...]] = {
    "reasoner": ("executor/skills", "executor/check_skill", "executor/run_skill", "executor/cancel_skill",
                 "executor/skill_result"),
    "executor": ("autopilot/command", "perception/localize_object", "perception/localize_placement"),
    # start a task, decide an approval, list and run one skill by hand (POST /vehicles/{id}/skills)
    "gateway": ("reasoner/start_task", "reasoner/cancel_task", "reasoner/task_result", "reasoner/decide_approval",
                "executor/skills", "executor/run_skill", "executor/cancel_skill", "executor/skill_result"),
}
# What a service publishes beyond the declarations' `publisher`: the gateway publishes the end of a task
# whose reasoner died (REASONER_TASK_STATUS names it only in a note).
SERVICE_ALSO_PUBLISHES: dict[str, tuple[str, ...]] = {"gateway": ("reasoner/task_status",)}


def service_access_control(identities: list[str], ros2_domains: dict[str, int] | None = None) -> dict[str, Any]:
    """Rules, subjects and policies giving each service identity (`<service>@<vehicle>`) the rights its job
    needs and no more: put on the topics it publishes, serve the queries it serves, ask the queries in
    SERVICE_ASKS, declare its own liveliness token, all on its own vehicle's keys (every vehicle's for
    `@fleet`). Observing (subscribe, read liveliness) and abort come from the template's policies for
    everyone, which `router_config` adds these subjects to. `ros2_domains`: the ROS 2 domain of each ros2
    identity (its graph and its service live outside aermani/v1)."""
    from shared.keys import ALIVE, HEALTH, HEARTBEAT, ROOT, declared_by

    rules: list[dict[str, Any]] = []
    subjects: list[dict[str, Any]] = []
    policies: list[dict[str, Any]] = []
    for identity in identities:
        m = SERVICE_IDENTITY.fullmatch(identity)
        if m is None:
            raise ConfigError(f"{identity!r} is not a service identity (<service>@<vehicle>)")
        service, vehicle = m["service"], m["vehicle"]
        prefix = f"{ROOT}/{'*' if vehicle == FLEET_SCOPE else vehicle}"
        topics, queries = declared_by(service)
        publish = sorted({t.name for t in topics} | set(SERVICE_ALSO_PUBLISHES.get(service, ())))
        publish += [f"{HEALTH}/{service}", f"{HEARTBEAT}/{service}"]
        sid = f"svc-{identity}"
        own: list[tuple[str, list[str], list[str]]] = [
            ("publish", ["put"], [f"{prefix}/{k}" for k in publish]),
            ("alive", ["liveliness_token"], [f"{prefix}/{ALIVE}/{service}"]),
        ]
        if queries:
            own.append(("serve", ["declare_queryable", "reply"], [f"{prefix}/{q.name}" for q in queries]))
        if SERVICE_ASKS.get(service):
            own.append(("ask", ["query"], [f"{prefix}/{k}" for k in SERVICE_ASKS[service]]))
        if service == "ros2" and ros2_domains is not None and identity in ros2_domains:
            domain = int(ros2_domains[identity])
            own.append(("ros2-graph", ["put", "declare_queryable", "reply"], [f"{domain}/**"]))
            own.append(("ros2-alive", ["liveliness_token"], [f"@ros2_lv/{domain}/**"]))
        names = []
        for what, messages, keys in own:
            rule_id = f"{sid}-{what}"
            rules.append({"id": rule_id, "permission": "allow", "flows": ["ingress"], "messages": messages,
                          "key_exprs": keys})
            names.append(rule_id)
        subjects.append({"id": sid, "cert_common_names": [SERVICE_CN_PREFIX + identity]})
        policies.append({"id": sid, "rules": names, "subjects": [sid]})
    return {"rules": rules, "subjects": subjects, "policies": policies}


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


# Template policies every service identity joins: receive everything, observe, publish abort.
EVERYONE_POLICIES = ("everyone-receives", "everyone-observes-and-aborts")


def router_config(role: str, certs_dir: str | Path, *, local: str | None = None, tls_listen: list[str] | None = None,
                  connect: list[str] | None = None, services: list[str] | None = None,
                  ros2_domains: dict[str, int] | None = None, vehicles: list[str] | None = None,
                  own: CertFiles | None = None) -> zenoh.Config:
    """The secure router config for `role` (ground or drone) from its template, with this deployment's
    certificates and endpoints. `local` is the plain loopback endpoint for the host's own services (must be
    loopback); `tls_listen` the mutual-TLS listeners (None keeps the template's); `connect` the routers to
    link to (the drone's ground router, tls/...).

    `services`: the service identities (`<service>@<vehicle>`, see `issue_service_certs`) that reach this
    router with certificates of their own. The router then has no plain listener at all (`local`, if given,
    is one more mutual-TLS listener, on loopback), the template's plain `local` subject is dropped, and each
    service gets only its own rights (`service_access_control`).

    `vehicles` (ground): bind each vehicle's router to its own vehicle id. A drone router then speaks with a
    certificate of its own, `router@<vehicle>` (`own`, from `issue_service_certs`), and the template's rights
    for the drone identity hold for that vehicle's keys only; the shared aermani-drone certificate keeps
    only what every identity has (observe, abort). `own`: this router's certificate instead of the role's."""
    if role not in ROLES:
        raise ConfigError(f"unknown router role {role!r}: use ground or drone")
    files = own if own is not None else check_cert_files(certs_dir, role)
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
    if tls_listen is not None:
        tls_eps = list(tls_listen)
    if services is not None:
        if local is not None and not local.startswith("tls/"):
            raise ConfigError(f"with service identities every listener is mutual TLS, not {local}")
        local_eps = []
        if local is not None:
            require_loopback([local], f"the {role} router's listener for its host's services")
            tls_eps.append(local)
    elif local is not None:
        local_eps = [local]
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
    if services is not None or vehicles is not None:
        acl = _access_control(role, json.loads(cfg.get_json("access_control")), services, ros2_domains, vehicles)
        cfg.insert_json5("access_control", json.dumps(acl))
    return cfg


def _access_control(role: str, acl: dict[str, Any], services: list[str] | None,
                    ros2_domains: dict[str, int] | None, vehicles: list[str] | None) -> dict[str, Any]:
    if vehicles is not None:
        acl = _bind_drones(acl, vehicles)
    elif role == "drone" and services is not None:
        # The vehicle's own services have their own identities; nobody reaching this router speaks as the
        # vehicle's router (it is this one), so the shared drone certificate gets no vehicle rights here.
        acl = _bind_drones(acl, [])
    if services is not None:
        acl = _with_services(acl, services, ros2_domains)
    return acl


VEHICLE_POLICY = "vehicle"  # the template's policy of the drone identity (ground.json5)


def _bind_drones(acl: dict[str, Any], vehicles: list[str]) -> dict[str, Any]:
    """The template's vehicle rights, once per vehicle, each for `router@<vehicle>` on that vehicle's keys."""
    from shared.keys import ROOT

    drone_cn = IDENTITIES["drone"]
    drone_ids = {s["id"] for s in acl["subjects"] if drone_cn in (s.get("cert_common_names") or [])}
    vehicle_rules = [r for pol in acl["policies"] if pol.get("id") == VEHICLE_POLICY for r in pol["rules"]]
    by_id = {r["id"]: r for r in acl["rules"]}
    routers = {vid: service_identity(ROUTER, vid) for vid in vehicles}
    policies = []
    for policy in acl["policies"]:
        if policy.get("id") == VEHICLE_POLICY:
            continue
        if policy.get("id") not in EVERYONE_POLICIES:
            policy = {**policy, "subjects": [s for s in policy["subjects"] if s not in drone_ids]}
        else:
            policy = {**policy, "subjects": [*policy["subjects"], *routers.values()]}
        if policy["subjects"]:
            policies.append(policy)
    for vid, router in routers.items():
        if vid == FLEET_SCOPE:
            raise ConfigError(f"invalid vehicle id {vid!r}")
        names = []
        for rule_id in vehicle_rules:
            rule = by_id[rule_id]
            keys = [k.replace(f"{ROOT}/*/", f"{ROOT}/{vid}/", 1) for k in rule["key_exprs"]]
            if any(k.startswith(f"{ROOT}/*") or not k.startswith(f"{ROOT}/{vid}/") for k in keys):
                raise ConfigError(f"rule {rule_id} of the vehicle policy names keys beyond one vehicle: {keys}")
            acl["rules"].append({**rule, "id": f"{rule_id}@{vid}", "key_exprs": keys})
            names.append(f"{rule_id}@{vid}")
        acl["subjects"].append({"id": router, "cert_common_names": [SERVICE_CN_PREFIX + router]})
        policies.append({"id": f"vehicle@{vid}", "rules": names, "subjects": [router]})
    acl["policies"] = policies
    return acl


def _with_services(acl: dict[str, Any], services: list[str], ros2_domains: dict[str, int] | None) -> dict[str, Any]:
    """The template's access control without its plain `local` subject, plus each service's own rights."""
    own = service_access_control(services, ros2_domains)
    plain = {s["id"] for s in acl["subjects"] if s.get("link_protocols")}
    acl["subjects"] = [s for s in acl["subjects"] if s["id"] not in plain] + own["subjects"]
    policies = []
    for policy in acl["policies"]:
        subjects = [s for s in policy["subjects"] if s not in plain]
        if policy.get("id") in EVERYONE_POLICIES:
            subjects += [s["id"] for s in own["subjects"]]
        if subjects:
            policies.append({**policy, "subjects": subjects})
    acl["rules"] = acl["rules"] + own["rules"]
    acl["policies"] = policies + own["policies"]
    return acl


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
