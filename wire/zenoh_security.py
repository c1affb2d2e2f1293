"""Zenoh security for a randt deployment: TLS/mTLS certificates, user/password, access control.

:func:`write_deployment` writes everything a deployment needs into one directory (``randt security
init DIR``; the recipe is ``docs/security.md``)::

    ca.pem                      the certificate authority every side trusts (ca.key: keep it offline)
    service.pem, service.key    the service's TLS certificate (CN randt-service, SAN = the hosts)
    <vehicle>.pem, <vehicle>.key  one client certificate per vehicle (CN = the vehicle id), for mTLS
    passwords.txt               the user/password dictionary (``user:password`` per line)
    service.json5               the service's Zenoh config: TLS listener, mTLS, usrpwd, access control
    router.json5                the same for a Zenoh router (zenohd), when vehicles reach a router
    service-client.json5        the service's config as a client of that router
    vehicle-<vehicle>.json5     each vehicle's config: its certificate, user and password

The access control (:func:`access_control`) is the heart: default **deny**, and per vehicle an allow
list derived from :mod:`randt.wire.keys`: a vehicle may put only on its own ``randt/fleet/<vehicle>/scan``,
read only its own poses, errors and corrections, the tiles and the service's liveliness token; only
the service's user may put poses, errors, corrections and tile updates, answer tile queries and hold
``randt/service/*``.
Zenoh checks a message's key expression against the rules with *inclusion* (a rule ``a/b/**``
allows ``a/b/c``, not ``a/*/c``), so a wildcard put (``randt/fleet/**``) matches no allow rule of a
vehicle and is denied. Subjects are bound by user name and, with mTLS, also by the certificate's
common name (both must match).

This module imports neither Zenoh nor, until certificates are made, ``cryptography`` (the
``security`` extra: ``pip install "randt-fleet[security]"``).
"""

from __future__ import annotations

import datetime as dt
import ipaddress
import json
import os
import secrets
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from randt.wire.ids import validate_id
from randt.wire.keys import ALL_SCANS, ROOT, correction_key, error_key, pose_key, scan_key

__all__ = [
    "EXAMPLE_DIRECTORY",
    "EXAMPLE_VEHICLES",
    "RESERVED_NAMES",
    "SERVICE_USER",
    "TLS_ONLY",
    "Deployment",
    "access_control",
    "example_configs",
    "make_certificates",
    "router_config",
    "service_client_config",
    "service_config",
    "vehicle_config",
    "write_deployment",
]

#: The user name (and certificate common name) of the service.
SERVICE_USER = "randt-service"

#: ``transport/link/protocols`` of every generated config: a session neither accepts nor opens a
#: link that is not encrypted (a password never crosses the network in clear; ``--listen tcp/...``
#: with such a config fails at start, "Unsupported protocol: tcp").
TLS_ONLY = ["tls", "quic"]

_ALL_SERVICE_TOKENS = f"{ROOT}/service/**"
_ALL_MAPS = f"{ROOT}/map/**"


def _rule(rule_id: str, flow: str, messages: list[str], keys: list[str]) -> dict[str, Any]:
    return {"id": rule_id, "permission": "allow", "flows": [flow], "messages": messages, "key_exprs": keys}


#: Names the files of :func:`write_deployment` use, so no vehicle may be called so.
RESERVED_NAMES = frozenset({"ca", "service", SERVICE_USER, "passwords", "router"})


def _check_vehicles(vehicles: Iterable[str]) -> tuple[str, ...]:
    checked = tuple(validate_id(v, "vehicle") for v in vehicles)
    if len(set(checked)) != len(checked):
        raise ValueError(f"vehicle ids must be distinct: {list(checked)}")
    reserved = sorted(RESERVED_NAMES & set(checked))
    if reserved:
        raise ValueError(f"vehicle ids {reserved} are reserved (names of the service's files and user)")
    return checked


def access_control(
    vehicles: Sequence[str], *, mtls: bool, service_subject: bool = False, service_user: str = SERVICE_USER
) -> dict[str, Any]:
    """The ``access_control`` section: default deny, one allow list per vehicle and one for the service.

    Parameters
    ----------
    vehicles:
        Vehicle ids (:mod:`randt.wire.ids`); each is also the vehicle's user name and certificate CN.
    mtls:
        Bind each subject to its certificate's common name as well as to its user name.
    service_subject:
        Give ``service_user`` the service's rights: for a router, to which the service connects as
        a client. The service's own ACL (peer mode) has no such subject: it publishes locally.
    service_user:
        The service's user name.
    """
    vehicles = _check_vehicles(vehicles)

    def subject(subject_id: str, name: str) -> dict[str, Any]:
        s: dict[str, Any] = {"id": subject_id, "usernames": [name]}
        if mtls:
            s["cert_common_names"] = [name]
        return s

    every = [
        "put", "delete", "declare_subscriber", "query", "reply", "declare_queryable",
        "liveliness_token", "liveliness_query", "declare_liveliness_subscriber",
    ]  # fmt: skip
    rules: list[dict[str, Any]] = [
        # the service (as a client of a router): everything under randt/, but no delete
        _rule("service-in", "ingress", [m for m in every if m != "delete"], [f"{ROOT}/**"]),
        _rule("service-out", "egress", [m for m in every if m != "delete"], [f"{ROOT}/**"]),
        # what every vehicle may receive: the service's scan subscriber (so its publisher sees a
        # match), tile updates and replies, the tile queryable, the service's liveliness token
        _rule("vehicle-out-common", "egress", ["declare_subscriber"], [ALL_SCANS]),
        _rule("vehicle-out-tiles", "egress", ["put", "reply", "declare_queryable"], [_ALL_MAPS]),
        _rule("vehicle-out-token", "egress", ["liveliness_token"], [_ALL_SERVICE_TOKENS]),
        # what every vehicle may ask for: tile subscriptions and queries, the service's token
        _rule("vehicle-in-tiles", "ingress", ["declare_subscriber", "query"], [_ALL_MAPS]),
        _rule(
            "vehicle-in-token",
            "ingress",
            ["liveliness_query", "declare_liveliness_subscriber"],
            [_ALL_SERVICE_TOKENS],
        ),
    ]
    subjects: list[dict[str, Any]] = []
    policies: list[dict[str, Any]] = []
    if service_subject:
        subjects.append(subject("service", service_user))
        policies.append({"id": "service", "rules": ["service-in", "service-out"], "subjects": ["service"]})
    else:
        rules = rules[2:]
    common = [r["id"] for r in rules if r["id"].startswith("vehicle-")]
    for v in vehicles:
        # what is said to this vehicle: its poses, its errors, the pose graph's corrections of its
        # keyframes (without the last, a vehicle of a secured deployment is never corrected)
        answers = [pose_key(v), error_key(v), correction_key(v)]
        rules += [
            _rule(f"{v}/scan", "ingress", ["put"], [scan_key(v)]),
            _rule(f"{v}/answers-in", "ingress", ["declare_subscriber"], answers),
            _rule(f"{v}/answers-out", "egress", ["put"], answers),
        ]
        subjects.append(subject(f"vehicle/{v}", v))
        policies.append(
            {
                "id": f"vehicle/{v}",
                "rules": [f"{v}/scan", f"{v}/answers-in", f"{v}/answers-out", *common],
                "subjects": [f"vehicle/{v}"],
            }
        )
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": rules,
        "subjects": subjects,
        "policies": policies,
    }


@dataclass(frozen=True)
class Deployment:
    """Where the files of :func:`write_deployment` are (paths as written into the configs)."""

    directory: Path
    vehicles: tuple[str, ...]
    passwords: dict[str, str] = field(repr=False)

    def path(self, name: str) -> Path:
        return self.directory / name

    @property
    def ca(self) -> Path:
        return self.path("ca.pem")

    @property
    def service_config(self) -> Path:
        return self.path("service.json5")

    @property
    def router_config(self) -> Path:
        return self.path("router.json5")

    @property
    def service_client_config(self) -> Path:
        return self.path("service-client.json5")

    def vehicle_config(self, vehicle: str) -> Path:
        return self.path(f"vehicle-{vehicle}.json5")


def _tls(directory: Path, *, listen: str | None, connect: str | None, mtls: bool) -> dict[str, Any]:
    tls: dict[str, Any] = {"root_ca_certificate": str(directory / "ca.pem"), "enable_mtls": mtls}
    if listen is not None:
        tls["listen_certificate"] = str(directory / f"{listen}.pem")
        tls["listen_private_key"] = str(directory / f"{listen}.key")
    if connect is not None:
        tls["connect_certificate"] = str(directory / f"{connect}.pem")
        tls["connect_private_key"] = str(directory / f"{connect}.key")
    return tls


def service_config(
    directory: Path,
    vehicles: Sequence[str],
    *,
    mtls: bool = True,
    usrpwd: bool = True,
    acl: bool = True,
    service_subject: bool = False,
) -> dict[str, Any]:
    """The service's config when vehicles connect to it (peer mode, the embedded default).

    The service listens with its certificate (on ``tls/`` endpoints), checks vehicles' passwords
    against ``passwords.txt`` (``usrpwd``) and, with ``mtls``, their certificates; its access
    control is :func:`access_control` (``acl``). Mode and endpoints come from randt's own settings
    (``--listen``, ``--connect``), not from this file.
    """
    transport: dict[str, Any] = {
        "link": {"protocols": TLS_ONLY, "tls": _tls(directory, listen="service", connect=None, mtls=mtls)}
    }
    if usrpwd:
        transport["auth"] = {"usrpwd": {"dictionary_file": str(directory / "passwords.txt")}}
    cfg: dict[str, Any] = {"transport": transport}
    if acl:
        cfg["access_control"] = access_control(vehicles, mtls=mtls, service_subject=service_subject)
    return cfg


def router_config(directory: Path, vehicles: Sequence[str], *, mtls: bool = True) -> dict[str, Any]:
    """A Zenoh router's config (``zenohd -c router.json5``): the service's certificate and the ACL.

    The router holds the access control, with the service's rights for ``randt-service``, which
    connects to it as a client (:func:`service_client_config`).
    """
    return {
        "mode": "router",
        "listen": {"endpoints": ["tls/[::]:7447"]},
        **service_config(directory, vehicles, mtls=mtls, service_subject=True),
    }


def service_client_config(directory: Path, password: str, *, mtls: bool = True) -> dict[str, Any]:
    """The service's config as a client of the router of :func:`router_config`."""
    return vehicle_config(directory, SERVICE_USER, password, mtls=mtls)


def vehicle_config(
    directory: Path, vehicle: str, password: str | None, *, mtls: bool = True
) -> dict[str, Any]:
    """A vehicle's config: trust the CA, present its certificate (``mtls``), its user and password
    (none: no ``usrpwd`` section)."""
    transport: dict[str, Any] = {
        "link": {
            "protocols": TLS_ONLY,
            "tls": _tls(directory, listen=None, connect=vehicle if mtls else None, mtls=mtls),
        }
    }
    if password is not None:
        transport["auth"] = {"usrpwd": {"user": vehicle, "password": password}}
    return {"transport": transport}


def _write_private(path: Path, data: bytes) -> None:
    """Write a secret readable by its owner only (created 0600, never world-readable in between)."""
    tmp = path.with_name(f".{path.name}.tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def _write_public(path: Path, data: bytes) -> None:
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_bytes(data)
    os.replace(tmp, path)


def make_certificates(
    directory: Path,
    *,
    server_hosts: Iterable[str] = ("localhost", "127.0.0.1"),
    clients: Iterable[str] = (),
    days: int = 365,
) -> None:
    """A CA (``ca.pem``/``ca.key``), a server certificate ``service.pem`` for ``server_hosts`` and a
    client certificate ``<name>.pem`` per client (CN = the name), all EC P-256, in ``directory``.

    A host that parses as an IP address goes into the certificate as an IP SAN, others as DNS names
    (Zenoh checks the name it dials against them unless ``verify_name_on_connect`` is false).
    """
    try:
        from cryptography import x509
        from cryptography.hazmat.primitives import hashes, serialization
        from cryptography.hazmat.primitives.asymmetric import ec
        from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID
    except ImportError as exc:  # pragma: no cover - depends on the install
        raise RuntimeError(
            'making certificates needs the cryptography package: pip install "randt-fleet[security]"'
        ) from exc

    directory.mkdir(parents=True, exist_ok=True)
    now = dt.datetime.now(dt.UTC) - dt.timedelta(minutes=5)
    until = now + dt.timedelta(days=days)

    def key_pem(key: ec.EllipticCurvePrivateKey) -> bytes:
        return key.private_bytes(
            serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
        )

    ca_key = ec.generate_private_key(ec.SECP256R1())
    ca_name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "randt-ca")])
    ca_cert = (
        x509.CertificateBuilder()
        .subject_name(ca_name)
        .issuer_name(ca_name)
        .public_key(ca_key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now)
        .not_valid_after(until)
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(
            x509.KeyUsage(
                digital_signature=True,
                key_cert_sign=True,
                crl_sign=True,
                content_commitment=False,
                key_encipherment=False,
                data_encipherment=False,
                key_agreement=False,
                encipher_only=False,
                decipher_only=False,
            ),
            critical=True,
        )
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(ca_key.public_key()), critical=False)
        .sign(ca_key, hashes.SHA256())
    )
    _write_private(directory / "ca.key", key_pem(ca_key))
    _write_public(directory / "ca.pem", ca_cert.public_bytes(serialization.Encoding.PEM))

    def leaf(name: str, hosts: Iterable[str], usage: list[x509.ObjectIdentifier]) -> None:
        key = ec.generate_private_key(ec.SECP256R1())
        sans: list[x509.GeneralName] = []
        for h in hosts:
            try:
                sans.append(x509.IPAddress(ipaddress.ip_address(h)))
            except ValueError:
                sans.append(x509.DNSName(h))
        builder = (
            x509.CertificateBuilder()
            .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, name)]))
            .issuer_name(ca_name)
            .public_key(key.public_key())
            .serial_number(x509.random_serial_number())
            .not_valid_before(now)
            .not_valid_after(until)
            .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
            .add_extension(x509.ExtendedKeyUsage(usage), critical=False)
            .add_extension(
                x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()), critical=False
            )
        )
        if sans:
            builder = builder.add_extension(x509.SubjectAlternativeName(sans), critical=False)
        cert = builder.sign(ca_key, hashes.SHA256())
        _write_private(directory / f"{name}.key", key_pem(key))
        _write_public(directory / f"{name}.pem", cert.public_bytes(serialization.Encoding.PEM))

    server_hosts = list(server_hosts)
    # the service's certificate serves both sides: it listens (server auth) and, as a client of a
    # router, presents it (client auth)
    leaf("service", server_hosts, [ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH])
    leaf(SERVICE_USER, [], [ExtendedKeyUsageOID.CLIENT_AUTH])
    for name in clients:
        leaf(name, [], [ExtendedKeyUsageOID.CLIENT_AUTH])


def write_deployment(
    directory: Path,
    vehicles: Sequence[str],
    *,
    hosts: Iterable[str] = ("localhost", "127.0.0.1"),
    mtls: bool = True,
    days: int = 365,
) -> Deployment:
    """Write certificates, passwords and every Zenoh config of a secured deployment (module docstring).

    ``hosts`` are the names and addresses vehicles dial the service (or router) by; each vehicle
    gets a random password. Secrets (keys, passwords, configs holding a password) are 0600.
    """
    vehicles = _check_vehicles(vehicles)
    directory = directory.resolve()
    make_certificates(directory, server_hosts=hosts, clients=vehicles, days=days)
    passwords = {name: secrets.token_urlsafe(24) for name in (SERVICE_USER, *vehicles)}
    _write_private(directory / "passwords.txt", "".join(f"{u}:{p}\n" for u, p in passwords.items()).encode())

    def dump(cfg: dict[str, Any]) -> bytes:
        return (json.dumps(cfg, indent=2) + "\n").encode()

    d = Deployment(directory, vehicles, passwords)
    _write_public(d.service_config, dump(service_config(directory, vehicles, mtls=mtls)))
    _write_public(d.router_config, dump(router_config(directory, vehicles, mtls=mtls)))
    service_client = service_client_config(directory, passwords[SERVICE_USER], mtls=mtls)
    _write_private(d.service_client_config, dump(service_client))
    for v in vehicles:
        _write_private(d.vehicle_config(v), dump(vehicle_config(directory, v, passwords[v], mtls=mtls)))
    return d


#: Where the examples of ``docs/security/`` keep their certificates (a deployment's directory).
EXAMPLE_DIRECTORY = Path("/etc/randt/zenoh")
#: The vehicles of the examples.
EXAMPLE_VEHICLES = ("car-01", "car-02")


def example_configs() -> dict[str, dict[str, Any]]:
    """The configs of ``docs/security/`` by file name: what :func:`write_deployment` writes for
    :data:`EXAMPLE_VEHICLES` in :data:`EXAMPLE_DIRECTORY`, passwords shown as placeholders.

    ``tests/wire/test_zenoh_security.py`` checks the committed files against this;
    ``python -m randt.wire.zenoh_security docs/security`` rewrites them.
    """
    d, vehicles = EXAMPLE_DIRECTORY, EXAMPLE_VEHICLES
    configs = {
        "service.json5": service_config(d, vehicles),
        "router.json5": router_config(d, vehicles),
        "service-client.json5": service_client_config(d, f"<{SERVICE_USER}'s password from passwords.txt>"),
    }
    for v in vehicles:
        configs[f"vehicle-{v}.json5"] = vehicle_config(d, v, f"<{v}'s password from passwords.txt>")
    return configs


def _write_examples(directory: Path) -> None:
    directory.mkdir(parents=True, exist_ok=True)
    for name, cfg in example_configs().items():
        (directory / name).write_text(json.dumps(cfg, indent=2) + "\n", encoding="utf-8")


if __name__ == "__main__":
    import sys

    _write_examples(Path(sys.argv[1]))
