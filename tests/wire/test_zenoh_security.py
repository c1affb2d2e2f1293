"""randt.wire.zenoh_security: the access control derived from the key expressions, the configs and the
files of a deployment (the sessions themselves are tested in tests/service/test_security.py)."""

from __future__ import annotations

import json
import stat
from pathlib import Path

import pytest
import zenoh
from cryptography import x509
from cryptography.x509.oid import NameOID

from randt.wire.zenoh_security import (
    EXAMPLE_DIRECTORY,
    SERVICE_USER,
    access_control,
    example_configs,
    write_deployment,
)

REPO = Path(__file__).resolve().parents[2]


def _allowed(acl: dict, subject_user: str, flow: str, message: str) -> set[str]:
    """Key expressions a user may use for ``message`` in ``flow`` under ``acl``."""
    subjects = {s["id"] for s in acl["subjects"] if subject_user in s["usernames"]}
    rule_ids = {r for p in acl["policies"] if subjects & set(p["subjects"]) for r in p["rules"]}
    return {
        k
        for r in acl["rules"]
        if r["id"] in rule_ids and flow in r["flows"] and message in r["messages"]
        for k in r["key_exprs"]
    }


def test_each_vehicle_may_put_only_its_own_scan_key() -> None:
    acl = access_control(["car-01", "car-02"], mtls=True)
    assert acl["enabled"] is True and acl["default_permission"] == "deny"
    assert _allowed(acl, "car-01", "ingress", "put") == {"randt/fleet/car-01/scan"}
    assert _allowed(acl, "car-02", "ingress", "put") == {"randt/fleet/car-02/scan"}
    assert _allowed(acl, "car-01", "ingress", "delete") == set()
    assert _allowed(acl, "car-01", "ingress", "liveliness_token") == set()
    assert _allowed(acl, "car-01", "ingress", "declare_queryable") == set()
    assert _allowed(acl, "car-01", "ingress", "reply") == set()
    # it reads its own answers (poses, errors, the pose graph's corrections), the tiles and the
    # service's token; not another vehicle's answers
    own = {"randt/fleet/car-01/pose", "randt/fleet/car-01/error", "randt/fleet/car-01/correction"}
    assert _allowed(acl, "car-01", "ingress", "declare_subscriber") == own | {"randt/map/**"}
    assert _allowed(acl, "car-01", "egress", "put") == own | {"randt/map/**"}
    # subjects: user name and certificate CN must both be the vehicle's
    car = next(s for s in acl["subjects"] if s["usernames"] == ["car-01"])
    assert car["cert_common_names"] == ["car-01"]
    assert "cert_common_names" not in next(
        s for s in access_control(["car-01"], mtls=False)["subjects"] if s["usernames"] == ["car-01"]
    )
    # the service's own ACL (peer mode) gives its user nothing; a router's gives it randt/**
    assert _allowed(acl, SERVICE_USER, "ingress", "put") == set()
    router_acl = access_control(["car-01"], mtls=True, service_subject=True)
    assert _allowed(router_acl, SERVICE_USER, "ingress", "put") == {"randt/**"}
    assert _allowed(router_acl, SERVICE_USER, "ingress", "delete") == set()
    # Zenoh itself accepts it (it checks every rule, subject and policy when it reads a config)
    zenoh.Config.from_json5(json.dumps({"access_control": router_acl}))


@pytest.mark.parametrize(
    ("vehicles", "match"),
    [
        (["car-01", "car-01"], "distinct"),
        (["a/b"], "vehicle"),
        (["*"], "vehicle"),
        ([SERVICE_USER], "reserved"),
        (["ca"], "reserved"),
    ],
)
def test_bad_vehicle_lists_are_refused(vehicles: list[str], match: str) -> None:
    with pytest.raises(ValueError, match=match):
        access_control(vehicles, mtls=True)


def test_the_committed_examples_are_the_generators() -> None:
    """docs/security/*.json5 are the generator's (``python -m randt.wire.zenoh_security docs/security``)."""
    examples = example_configs()
    committed = {p.name: json.loads(p.read_text()) for p in (REPO / "docs" / "security").glob("*.json5")}
    assert committed == examples, "regenerate: python -m randt.wire.zenoh_security docs/security"
    for name in examples:  # each is a valid Zenoh config
        zenoh.Config.from_json5((REPO / "docs" / "security" / name).read_text())
    assert str(EXAMPLE_DIRECTORY) in (REPO / "docs" / "security.md").read_text()


def test_write_deployment_files_and_modes(tmp_path: Path) -> None:
    d = write_deployment(tmp_path / "dep", ["car-01"], hosts=["fleet.example.org", "10.0.0.5"], days=30)
    names = {p.name for p in d.directory.iterdir()}
    assert names == {
        "ca.pem", "ca.key", "service.pem", "service.key", f"{SERVICE_USER}.pem", f"{SERVICE_USER}.key",
        "car-01.pem", "car-01.key", "passwords.txt",
        "service.json5", "router.json5", "service-client.json5", "vehicle-car-01.json5",
    }  # fmt: skip
    for name in ("ca.key", "service.key", "car-01.key", "passwords.txt", "vehicle-car-01.json5"):
        assert stat.S_IMODE((d.directory / name).stat().st_mode) == 0o600, name
    users = dict(line.split(":", 1) for line in (d.directory / "passwords.txt").read_text().splitlines())
    assert users == d.passwords and set(users) == {SERVICE_USER, "car-01"}
    assert len(set(users.values())) == 2 and all(len(p) >= 32 for p in users.values())
    vehicle = json.loads(d.vehicle_config("car-01").read_text())
    assert vehicle["transport"]["auth"]["usrpwd"] == {"user": "car-01", "password": d.passwords["car-01"]}
    # certificates: CNs, the service's names and addresses, signed by the CA
    ca = x509.load_pem_x509_certificate((d.directory / "ca.pem").read_bytes())
    server = x509.load_pem_x509_certificate((d.directory / "service.pem").read_bytes())
    client = x509.load_pem_x509_certificate((d.directory / "car-01.pem").read_bytes())
    assert client.subject.get_attributes_for_oid(NameOID.COMMON_NAME)[0].value == "car-01"
    sans = server.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert sans.get_values_for_type(x509.DNSName) == ["fleet.example.org"]
    assert [str(a) for a in sans.get_values_for_type(x509.IPAddress)] == ["10.0.0.5"]
    for cert in (server, client):
        cert.verify_directly_issued_by(ca)
        assert 29 <= (cert.not_valid_after_utc - cert.not_valid_before_utc).days <= 30
