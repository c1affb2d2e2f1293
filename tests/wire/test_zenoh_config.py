"""Tests for wire.zenoh_config: the one Zenoh configuration of the service, vehicles and tests."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from wire.zenoh_config import check_endpoints, zenoh_config


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
    code = "import sys, wire, wire.keys, wire.ids, wire.codes, wire.messages; print('zenoh' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "False"
