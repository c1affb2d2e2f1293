"""Zenoh security on loopback with real sessions: TLS, mTLS, user/password, access control.

Every certificate, password and config comes from ``randt.wire.zenoh_security`` (what ``randt security
init`` writes and ``docs/security.md`` recommends), so the recipe itself is what is tested. The
service side is a Zenoh session configured as the service configures its own
(``randt.wire.zenoh_config.zenoh_config`` with ``config_file``); ``test_impersonation.py`` runs the real
service. Each access-control case runs with the ACL on and, as a control, off: the control shows
the forged messages do arrive without it, so the checks can fail.
"""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Callable
from pathlib import Path

import pytest
import zenoh

from randt.wire.keys import ALL_SCANS, correction_key, pose_key, scan_key, service_token_key, tile_key
from randt.wire.zenoh_security import (
    Deployment,
    make_certificates,
    router_config,
    service_config,
    vehicle_config,
    write_deployment,
)
from tests.service.security import (
    linked_identities,
    open_session,
    refused,
    tls_endpoint,
    wait_for,
    write_config,
)

VEHICLES = ("victim", "evil")


@pytest.fixture(scope="module")
def deployment(tmp_path_factory: pytest.TempPathFactory) -> Deployment:
    return write_deployment(tmp_path_factory.mktemp("zenoh-security"), VEHICLES)


@pytest.fixture(scope="module")
def stranger(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Certificates of another CA, with the same names (a client CN ``victim`` too)."""
    directory = tmp_path_factory.mktemp("other-ca")
    make_certificates(directory, clients=["victim"])
    return directory


class Inbox:
    """Samples received by subscribers, thread-safe."""

    def __init__(self) -> None:
        self.samples: list[tuple[str, str, bytes]] = []
        self._lock = threading.Lock()

    def callback(self, who: str):
        def on_sample(sample: zenoh.Sample) -> None:
            with self._lock:
                self.samples.append((who, str(sample.key_expr), sample.payload.to_bytes()))

        return on_sample

    def keys(self, who: str) -> list[str]:
        with self._lock:
            return [k for w, k, _ in self.samples if w == who]

    def payloads(self, who: str) -> list[bytes]:
        with self._lock:
            return [p for w, _, p in self.samples if w == who]


def test_tls_vehicle_must_trust_the_service_certificate(
    deployment: Deployment, stranger: Path, tmp_path
) -> None:
    d = deployment.directory
    endpoint = tls_endpoint()
    service_file = write_config(
        tmp_path / "s.json5", service_config(d, [], mtls=False, usrpwd=False, acl=False)
    )
    trusting = write_config(tmp_path / "v.json5", vehicle_config(d, "victim", None, mtls=False))
    doubting = vehicle_config(d, "victim", None, mtls=False)
    doubting["transport"]["link"]["tls"]["root_ca_certificate"] = str(stranger / "ca.pem")
    doubting_file = write_config(tmp_path / "doubting.json5", doubting)
    inbox = Inbox()
    service = open_session(service_file, "peer", listen=(endpoint,))
    try:
        service.declare_subscriber(ALL_SCANS, inbox.callback("service"))
        vehicle = open_session(trusting, "client", connect=(endpoint,))
        try:
            publisher = vehicle.declare_publisher(scan_key("victim"))
            assert wait_for(lambda: publisher.matching_status.matching)
            publisher.put(b"over tls")
            assert wait_for(lambda: inbox.payloads("service") == [b"over tls"])
        finally:
            vehicle.close()
        # a vehicle that does not trust the service's CA does not connect (it could be anyone's)
        assert "Unable to connect" in refused(doubting_file, endpoint)
        # nor does a plain TCP client reach the TLS listener
        assert "Unable to connect" in refused(
            write_config(tmp_path / "plain.json5", {}), endpoint.replace("tls/", "tcp/")
        )
    finally:
        service.close()


def test_mtls_lets_in_only_a_certificate_of_the_ca(deployment: Deployment, stranger: Path, tmp_path) -> None:
    d = deployment.directory
    endpoint = tls_endpoint()
    service_file = write_config(
        tmp_path / "s.json5", service_config(d, [], mtls=True, usrpwd=False, acl=False)
    )
    with_cert = write_config(tmp_path / "v.json5", vehicle_config(d, "victim", None, mtls=True))
    without = write_config(tmp_path / "none.json5", vehicle_config(d, "victim", None, mtls=False))
    foreign = vehicle_config(d, "victim", None, mtls=True)
    foreign["transport"]["link"]["tls"]["connect_certificate"] = str(stranger / "victim.pem")
    foreign["transport"]["link"]["tls"]["connect_private_key"] = str(stranger / "victim.key")
    foreign_file = write_config(tmp_path / "foreign.json5", foreign)
    service = open_session(service_file, "peer", listen=(endpoint,))
    try:
        vehicle = open_session(with_cert, "client", connect=(endpoint,))
        try:
            # the service knows who is on the link: the certificate's common name
            assert wait_for(lambda: linked_identities(service) == ["victim"])
        finally:
            vehicle.close()
        assert "Unable to connect" in refused(without, endpoint)
        assert "Unable to connect" in refused(foreign_file, endpoint)  # CN victim, signed by another CA
    finally:
        service.close()


def test_user_password_is_checked(deployment: Deployment, tmp_path) -> None:
    d = deployment.directory
    endpoint = tls_endpoint()
    service_file = write_config(
        tmp_path / "s.json5", service_config(d, [], mtls=False, usrpwd=True, acl=False)
    )
    right = write_config(
        tmp_path / "right.json5", vehicle_config(d, "victim", deployment.passwords["victim"], mtls=False)
    )
    wrong = write_config(
        tmp_path / "wrong.json5", vehicle_config(d, "victim", "not-the-password", mtls=False)
    )
    other = write_config(
        tmp_path / "other.json5", vehicle_config(d, "victim", deployment.passwords["evil"], mtls=False)
    )
    anonymous = write_config(tmp_path / "anon.json5", vehicle_config(d, "victim", None, mtls=False))
    service = open_session(service_file, "peer", listen=(endpoint,))
    try:
        open_session(right, "client", connect=(endpoint,)).close()
        for config in (wrong, other, anonymous):
            assert "Unable to connect" in refused(config, endpoint), config.name
    finally:
        service.close()


def _acl_scenario(deployment: Deployment, tmp_path: Path, *, topology: str, acl: bool) -> dict[str, object]:
    """The service (peer, or a client of a router holding the ACL), the victim, and an attacker with
    valid credentials of its own (``evil``) and a chimera (the victim's password, evil's
    certificate) trying to act as the victim and as the service. Returns what everybody received."""
    d = deployment.directory
    endpoint = tls_endpoint()
    pw = deployment.passwords
    if topology == "peer":
        hub_cfg = service_config(d, VEHICLES, acl=acl)
    else:
        hub_cfg = router_config(d, VEHICLES)
        if not acl:
            del hub_cfg["access_control"]
    hub_file = write_config(tmp_path / "hub.json5", hub_cfg)
    victim_file = write_config(tmp_path / "victim.json5", vehicle_config(d, "victim", pw["victim"]))
    evil_file = write_config(tmp_path / "evil.json5", vehicle_config(d, "evil", pw["evil"]))
    chimera = vehicle_config(d, "evil", pw["evil"])
    chimera["transport"]["auth"]["usrpwd"] = {"user": "victim", "password": pw["victim"]}
    chimera_file = write_config(tmp_path / "chimera.json5", chimera)

    inbox = Inbox()
    sessions: list[zenoh.Session] = []
    try:
        if topology == "peer":
            service = open_session(hub_file, "peer", listen=(endpoint,))
            sessions.append(service)
        else:
            sessions.append(open_session(hub_file, "router", listen=(endpoint,)))
            client_file = write_config(
                tmp_path / "service-client.json5", json.loads(deployment.service_client_config.read_text())
            )
            service = open_session(client_file, "client", connect=(endpoint,))
            sessions.append(service)
        handles: list[object] = [  # kept: a dropped handle may undeclare its entity
            service.declare_subscriber(ALL_SCANS, inbox.callback("service")),
            service.declare_queryable(tile_key("*", "*"), lambda q: q.reply(q.key_expr, b"tile by query")),
            service.liveliness().declare_token(service_token_key("randt-1")),
        ]

        victim, evil, chimera_s = (
            open_session(f, "client", connect=(endpoint,)) for f in (victim_file, evil_file, chimera_file)
        )
        sessions += [victim, evil, chimera_s]
        handles += [
            victim.declare_subscriber(pose_key("victim"), inbox.callback("victim pose")),
            victim.declare_subscriber("randt/map/**", inbox.callback("victim tiles")),
            victim.liveliness().declare_subscriber(
                "randt/service/**", inbox.callback("victim tokens"), history=True
            ),
            victim.declare_subscriber(correction_key("victim"), inbox.callback("victim correction")),
            evil.declare_subscriber(pose_key("victim"), inbox.callback("evil reads victim pose")),
            evil.declare_subscriber(correction_key("victim"), inbox.callback("evil reads victim correction")),
        ]
        publisher = victim.declare_publisher(scan_key("victim"))
        assert wait_for(lambda: publisher.matching_status.matching), "the victim never saw the service"
        assert wait_for(lambda: len(inbox.payloads("victim tokens")) >= 1)
        time.sleep(0.3)  # the subscribers' declarations reach the service

        publisher.put(b"real scan")
        evil.put(scan_key("evil"), b"evil's own scan")
        evil.put(scan_key("victim"), b"forged scan")
        evil.put("randt/fleet/**", b"forged wildcard scan")
        chimera_s.put(scan_key("victim"), b"chimera scan")
        evil.put(pose_key("victim"), b"forged pose")
        evil.put(tile_key("default", "0_0"), b"forged tile")
        handles.append(evil.liveliness().declare_token(service_token_key("fake")))
        service.put(pose_key("victim"), b"real pose")
        service.put(correction_key("victim"), b"real correction")
        service.put(tile_key("default", "0_0"), b"real tile")

        def arrived(who: str, *payloads: bytes) -> Callable[[], bool]:
            return lambda: set(payloads) <= set(inbox.payloads(who))

        real = [
            arrived("service", b"real scan", b"evil's own scan"),
            arrived("victim pose", b"real pose"),
            arrived("victim correction", b"real correction"),
            arrived("victim tiles", b"real tile"),
        ]
        forged = [
            arrived("service", b"forged scan", b"forged wildcard scan", b"chimera scan"),
            arrived("victim pose", b"forged pose"),
            arrived("victim tiles", b"forged tile"),
            lambda: service_token_key("fake") in inbox.keys("victim tokens"),
        ]
        wait_for(lambda: all(c() for c in real), 20)
        if acl:
            time.sleep(1.0)  # what is forged gets time to arrive (it must not)
        else:
            wait_for(lambda: all(c() for c in forged), 20)
        replies = [r.ok.payload.to_bytes() for r in victim.get(tile_key("default", "0_0"), timeout=5) if r.ok]
        # (the liveliness subscriber, not a liveliness get: a get came back empty 1 time in 6)
        tokens = sorted(set(inbox.keys("victim tokens")))
        return {
            "service": sorted(inbox.payloads("service")),
            "victim pose": sorted(inbox.payloads("victim pose")),
            "victim correction": inbox.payloads("victim correction"),
            "evil reads victim correction": inbox.payloads("evil reads victim correction"),
            "victim tiles": sorted(inbox.payloads("victim tiles")),
            "evil reads victim pose": inbox.payloads("evil reads victim pose"),
            "tile replies": replies,
            "tokens": tokens,
            "identities": linked_identities(sessions[0]),
        }
    finally:
        for s in reversed(sessions):
            s.close()


@pytest.mark.parametrize("topology", ["peer", "router"])
def test_acl_binds_keys_to_credentials(deployment: Deployment, tmp_path, topology: str) -> None:
    got = _acl_scenario(deployment, tmp_path, topology=topology, acl=True)
    # the service hears each vehicle only on its own scan key: nothing forged, nothing wildcarded
    assert got["service"] == [b"evil's own scan", b"real scan"]
    # only the service's poses, tiles and token reach a vehicle
    assert got["victim pose"] == [b"real pose"]
    assert got["victim correction"] == [b"real correction"]  # (once denied: issue 33)
    assert got["victim tiles"] == [b"real tile"]
    assert got["tokens"] == ["randt/service/randt-1"]
    assert got["tile replies"] == [b"tile by query"]
    # a vehicle cannot read another's poses
    # (what evil's session delivers to itself locally is its own forgeries)
    assert sorted(got["evil reads victim pose"]) == [b"forged pose", b"forged wildcard scan"]
    assert got["evil reads victim correction"] == [b"forged wildcard scan"]  # nor its corrections
    # the hub knows the links by certificate CN (the chimera's is evil's)
    expected = ["evil", "evil", "victim"] + (["randt-service"] if topology == "router" else [])
    assert got["identities"] == sorted(expected)


@pytest.mark.parametrize("topology", ["peer", "router"])
def test_without_the_acl_the_forgeries_arrive(deployment: Deployment, tmp_path, topology: str) -> None:
    """The control: the same credentials without access control let every forgery through."""
    got = _acl_scenario(deployment, tmp_path, topology=topology, acl=False)
    assert {b"forged scan", b"forged wildcard scan", b"chimera scan"} <= set(got["service"])
    assert b"forged pose" in got["victim pose"]
    assert b"forged tile" in got["victim tiles"]
    assert got["tokens"] == ["randt/service/fake", "randt/service/randt-1"]
    assert b"real pose" in got["evil reads victim pose"]
    assert b"real correction" in got["evil reads victim correction"]


def test_a_generated_config_opens_no_cleartext_link(deployment: Deployment, tmp_path) -> None:
    """``transport/link/protocols`` is TLS (or QUIC) only: the service cannot listen on ``tcp/`` and
    a vehicle does not connect to a ``tcp/`` endpoint, so a password never crosses in clear."""
    endpoint = tls_endpoint().replace("tls/", "tcp/")
    with pytest.raises(ValueError, match=f"endpoint {endpoint} uses tcp, which Zenoh config file"):
        open_session(deployment.service_config, "peer", listen=(endpoint,)).close()  # refused by randt
    raw = zenoh.Config.from_file(str(deployment.service_config))  # and by Zenoh itself
    raw.insert_json5("listen/endpoints", json.dumps([endpoint]))
    raw.insert_json5("scouting/multicast/enabled", "false")
    with pytest.raises(zenoh.ZError, match="Unsupported protocol: tcp"):
        zenoh.open(raw).close()
    plain = open_session(write_config(tmp_path / "plain.json5", {}), "peer", listen=(endpoint,))
    try:
        open_session(write_config(tmp_path / "other.json5", {}), "client", connect=(endpoint,)).close()
        assert f"endpoint {endpoint} uses tcp" in refused(deployment.vehicle_config("victim"), endpoint)
        raw = zenoh.Config.from_file(str(deployment.vehicle_config("victim")))  # Zenoh alone too
        raw.insert_json5("mode", '"client"')
        raw.insert_json5("connect/endpoints", json.dumps([endpoint]))
        raw.insert_json5("scouting/multicast/enabled", "false")
        with pytest.raises(zenoh.ZError, match="Unable to connect"):
            zenoh.open(raw).close()
    finally:
        plain.close()
