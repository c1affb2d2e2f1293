"""Tests for randt.wire.zenoh_config: the one Zenoh configuration of the service, vehicles and tests."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from randt.wire.zenoh_config import check_endpoints, load_config_file, zenoh_config


def test_config_has_explicit_endpoints_and_no_multicast_scouting() -> None:
    cfg = zenoh_config(
        "peer", listen=("tcp/127.0.0.1:7447",), connect=("tcp/10.0.0.5:7447", "udp/[::1]:7448")
    )
    assert json.loads(cfg.get_json("mode")) == "peer"
    assert json.loads(cfg.get_json("scouting/multicast/enabled")) is False
    assert json.loads(cfg.get_json("listen/endpoints")) == ["tcp/127.0.0.1:7447"]
    assert json.loads(cfg.get_json("connect/endpoints")) == ["tcp/10.0.0.5:7447", "udp/[::1]:7448"]
    assert json.loads(zenoh_config("client").get_json("mode")) == "client"


def test_bad_modes_and_endpoints_are_refused() -> None:
    with pytest.raises(ValueError, match="Zenoh mode must be client, peer or router, got 'server'"):
        zenoh_config("server")
    for bad in ("127.0.0.1:7447", "http/127.0.0.1:80", "tcp/", "tcp/a b", ""):
        with pytest.raises(ValueError, match="not a Zenoh endpoint"):
            check_endpoints([bad])
        with pytest.raises(ValueError, match="not a Zenoh endpoint"):
            zenoh_config("peer", connect=(bad,))
    ok = ["tcp/127.0.0.1:7447", "udp/10.0.0.1:7447", "quic/h:1", "tls/h:1", "ws/h:1", "unixsock-stream/s"]
    assert check_endpoints(ok) == tuple(ok)


def test_only_the_zenoh_helper_imports_zenoh() -> None:
    """``import wire`` (messages, keys, ids, codes) must not load Zenoh."""
    code = (
        "import sys, randt.wire, randt.wire.keys, randt.wire.ids, randt.wire.codes, randt.wire.messages; "
        "print('zenoh' in sys.modules)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "False"


def test_a_config_file_is_the_base_and_randt_sets_mode_endpoints_and_scouting(tmp_path, caplog) -> None:
    path = tmp_path / "z.json5"
    path.write_text(
        """{
          // a native Zenoh config, comments and all
          mode: "router",
          listen: { endpoints: ["tcp/0.0.0.0:7447"] },
          scouting: { multicast: { enabled: true } },
          transport: { unicast: { max_sessions: 17 }, auth: { usrpwd: { user: "car-01", password: "pw" } } },
        }"""
    )
    with caplog.at_level("WARNING", logger="randt.wire.zenoh_config"):
        cfg = zenoh_config("client", connect=("tls/10.0.0.5:7447",), config_file=path)
    assert json.loads(cfg.get_json("transport/unicast/max_sessions")) == 17  # the file's
    assert json.loads(cfg.get_json("transport/auth/usrpwd/user")) == "car-01"
    assert json.loads(cfg.get_json("mode")) == "client"  # ours
    assert json.loads(cfg.get_json("listen/endpoints")) == []  # ours, even empty
    assert json.loads(cfg.get_json("connect/endpoints")) == ["tls/10.0.0.5:7447"]
    assert json.loads(cfg.get_json("scouting/multicast/enabled")) is False
    warned = sorted(r.getMessage().split(" sets ")[1].split(" to ")[0] for r in caplog.records)
    assert warned == ["listen/endpoints", "mode", "scouting/multicast/enabled"]
    # a file that agrees with the settings is not warned about
    caplog.clear()
    path.write_text('{mode: "peer", listen: {endpoints: ["tcp/127.0.0.1:7447"]}}')
    with caplog.at_level("WARNING", logger="randt.wire.zenoh_config"):
        zenoh_config("peer", listen=("tcp/127.0.0.1:7447",), config_file=path)
    assert caplog.records == []


def test_a_bad_config_file_is_one_clear_error(tmp_path) -> None:
    with pytest.raises(ValueError, match=r"Zenoh config file '.*missing.json5' does not exist"):
        load_config_file(tmp_path / "missing.json5")
    bad = tmp_path / "bad.json5"
    bad.write_text('{transport: {link: {tls: {server_certificate: "x.pem"}}}}')  # a Zenoh 0.x key
    with pytest.raises(ValueError, match=r"bad.json5' is not valid: .*unknown field `server_certificate`"):
        zenoh_config("peer", config_file=bad)
    acl = tmp_path / "acl.json5"
    acl.write_text('{access_control: {enabled: true, rules: [{id: "r", permission: "allow"}]}}')
    with pytest.raises(ValueError, match="missing field `key_exprs`"):
        load_config_file(acl)
