"""Defect 4 of issue 13: any Zenoh peer could act as any vehicle.

The real service (``randt.service.runtime.Service``) runs with the Zenoh config ``randt security init``
writes (TLS, mTLS, user/password, access control). Another vehicle, with valid credentials of its
own, publishes a scan as vehicle ``victim``, session ``v1``, seq 2^62 (before, accepted: the
victim's trajectory gained a pose and every later real scan was refused as out of order), a pose
on the victim's key, a tile update and the service's liveliness token. With the access control the
service never processes the forged scan, the victim's later scans are all accepted and it receives
nothing forged. The control (same credentials, no access control) reproduces the defect.
"""

from __future__ import annotations

import contextlib
import threading

import numpy as np
import pytest
import zenoh

from randt.clients.publisher import PublisherSettings, VehiclePublisher
from randt.core.errors import BadMessageError
from randt.service.runtime import Service
from randt.service.settings import ServiceSettings
from randt.sim.drive import simulate_fleet
from randt.sim.town import Town
from randt.wire.codes import ErrorCode
from randt.wire.keys import error_key, pose_key, scan_key, service_token_key, tile_key
from randt.wire.messages import (
    ErrorMessage,
    PoseMessage,
    decode_error,
    decode_pose,
    encode,
    scan_from_arrays,
)
from randt.wire.zenoh_security import Deployment, service_config, write_deployment
from tests.service.security import open_session, tls_endpoint, wait_for, write_config

FORGED_SEQ = 2**62


@pytest.fixture(scope="module")
def deployment(tmp_path_factory: pytest.TempPathFactory) -> Deployment:
    return write_deployment(tmp_path_factory.mktemp("zenoh-security"), ["victim", "evil"])


@pytest.fixture(scope="module")
def scans():
    town = Town.generate(2)
    return [scan for _, scan in simulate_fleet(town, 1, n_scans=6, seed=3, speed_mps=6.0)]


def _scan(scans, seq: int, *, vehicle: str = "victim", session: str = "v1") -> bytes:
    scan = scans[min(seq, len(scans) - 1)]
    prior = scan.T_world_sensor if seq == 0 else None
    stamp = scan.stamp_ns if seq < len(scans) else scans[-1].stamp_ns + 10**9
    return encode(
        scan_from_arrays(
            vehicle,
            session,
            seq,
            stamp,
            scan.points_xyz,
            intensity=scan.intensity,
            prior_pose=prior,
            prior_covariance=np.diag([0.05**2] * 3 + [np.radians(0.2) ** 2] * 3)
            if prior is not None
            else None,
        )
    )


@pytest.mark.parametrize("acl", [True, False], ids=["acl", "control-without-acl"])
def test_a_vehicle_cannot_publish_as_another(deployment: Deployment, scans, tmp_path, acl: bool) -> None:
    endpoint = tls_endpoint()
    if acl:
        config = deployment.service_config  # the file randt security init wrote, as written
    else:
        config = write_config(
            tmp_path / "no-acl.json5", service_config(deployment.directory, deployment.vehicles, acl=False)
        )
    settings = ServiceSettings(
        data_dir=tmp_path / "data",
        zenoh_mode="peer",
        listen=(endpoint,),
        zenoh_config=config,
        matcher_processes=0,
        flush_interval_s=0.5,
    )
    service = Service(settings)
    service.start()
    answers: list[PoseMessage | ErrorMessage] = []
    raw_poses: list[bytes] = []
    tokens: list[str] = []
    lock = threading.Lock()

    def on_pose(sample: zenoh.Sample) -> None:
        payload = sample.payload.to_bytes()
        with lock:
            raw_poses.append(payload)
            with contextlib.suppress(BadMessageError):  # a forged pose that is not even a pose
                answers.append(decode_pose(payload))

    def on_error(sample: zenoh.Sample) -> None:
        with lock:
            answers.append(decode_error(sample.payload.to_bytes()))

    evil_errors: list[ErrorMessage] = []
    victim = evil = None
    try:
        victim = open_session(deployment.vehicle_config("victim"), "client", connect=(endpoint,))
        evil = open_session(deployment.vehicle_config("evil"), "client", connect=(endpoint,))
        handles: list[object] = [
            victim.declare_subscriber(pose_key("victim"), on_pose),
            victim.declare_subscriber(error_key("victim"), on_error),
            victim.liveliness().declare_subscriber(
                "randt/service/**", lambda s: tokens.append(str(s.key_expr)), history=True
            ),
            evil.declare_subscriber(
                error_key("evil"), lambda s: evil_errors.append(decode_error(s.payload.to_bytes()))
            ),
        ]
        # BLOCK, as the vehicle library sends: zenoh's default (DROP) discards a put that finds
        # the transmit queue full, which two 1.9 MB puts in a row do on a loaded machine
        block = zenoh.CongestionControl.BLOCK
        publisher = victim.declare_publisher(scan_key("victim"), congestion_control=block)
        assert wait_for(lambda: publisher.matching_status.matching, 30), "the victim never saw the service"
        assert service.sessions.wait_matchers(120)

        def answered(n: int) -> bool:
            with lock:
                return len(answers) >= n

        for seq in range(3):
            publisher.put(_scan(scans, seq))
        assert wait_for(lambda: answered(3), 120), answers

        # the attack: valid credentials of its own, the victim's key and session, seq 2^62
        evil.put(scan_key("victim"), _scan(scans, FORGED_SEQ), congestion_control=block)
        # on its own key (which the ACL lets it use) a message that names the victim: the service
        # checks the message's vehicle against the key, so this is refused too
        evil.put(scan_key("evil"), _scan(scans, FORGED_SEQ), congestion_control=block)
        evil.put(pose_key("victim"), b"forged pose", congestion_control=block)
        evil.put(tile_key("default", "0_0"), b"forged tile", congestion_control=block)
        handles.append(evil.liveliness().declare_token(service_token_key("fake")))
        wait_for(lambda: answered(4), 3)  # without the ACL the forged scan gets its pose

        for seq in range(3, 6):
            publisher.put(_scan(scans, seq))
        assert wait_for(lambda: sum(a.seq in range(3, 6) for a in answers) >= 3, 120), answers
        trajectory = service.sessions.trajectory("victim", "v1")
        assert trajectory is not None
        with lock:
            by_seq = {a.seq: a for a in answers}
            forged_pose_seen = b"forged pose" in raw_poses
        assert wait_for(lambda: len(evil_errors) >= 1, 30)
        assert [(e.vehicle, e.seq, e.code) for e in evil_errors] == [
            ("evil", FORGED_SEQ, ErrorCode.INVALID_FIELD)
        ]
        assert "message says 'victim'" in evil_errors[0].reason
        if acl:
            assert sorted(by_seq) == [0, 1, 2, 3, 4, 5], answers  # nothing answered for 2^62
            assert all(isinstance(a, PoseMessage) for a in answers), answers  # no out_of_order
            assert len(trajectory[0]) == 6  # the forged scan never reached the session
            assert not forged_pose_seen
            assert sorted(set(tokens)) == [service_token_key(settings.instance)]
        else:  # the defect, as reported
            assert isinstance(by_seq[FORGED_SEQ], PoseMessage)
            assert all(
                isinstance(by_seq[s], ErrorMessage) and by_seq[s].code == ErrorCode.OUT_OF_ORDER
                for s in (3, 4, 5)
            ), answers
            assert forged_pose_seen
            assert service_token_key("fake") in tokens
        del handles
    finally:
        for s in (evil, victim):
            if s is not None:
                s.close()
        service.stop()


def test_the_vehicle_library_streams_over_the_secured_service(
    deployment: Deployment, scans, tmp_path
) -> None:
    """``VehiclePublisher`` with ``RANDT_VEHICLE_ZENOH_CONFIG``'s setting: the victim's scans are
    acknowledged; the same library with evil's credentials publishing as ``victim`` gets no answer."""
    endpoint = tls_endpoint()
    settings = ServiceSettings(
        data_dir=tmp_path / "data",
        listen=(endpoint,),
        zenoh_config=deployment.service_config,
        matcher_processes=0,
    )
    service = Service(settings)
    service.start()
    try:
        assert service.sessions.wait_matchers(120)
        stats = {}
        for name, config, timeout in (("victim", "victim", 60.0), ("impostor", "evil", 5.0)):
            publisher_settings = PublisherSettings(
                connect=(endpoint,), zenoh_config=deployment.vehicle_config(config), answer_timeout_s=timeout
            )
            with VehiclePublisher("victim", f"lib-{name}", settings=publisher_settings) as pub:
                assert pub.wait_connected(30), name
                for i, scan in enumerate(scans[:3]):
                    pub.publish(
                        scan.points_xyz,
                        scan.stamp_ns,
                        intensity=scan.intensity,
                        prior_pose=scan.T_world_sensor if i == 0 else None,
                        prior_covariance=np.diag([0.05**2] * 3 + [np.radians(0.2) ** 2] * 3)
                        if i == 0
                        else None,
                    )
                pub.flush(90)
                stats[name] = pub.close()
        assert (stats["victim"].acknowledged, stats["victim"].rejected) == (3, 0)
        assert (stats["impostor"].acknowledged, stats["impostor"].rejected, stats["impostor"].lost) == (
            0,
            0,
            3,
        )
        assert service.sessions.trajectory("victim", "lib-impostor") is None
    finally:
        service.stop()
