"""Fixtures for service tests: a real Zenoh router on loopback, free ports, simulated fleets."""

from __future__ import annotations

import socket
from collections.abc import Iterator

import pytest
import zenoh

from randt.wire.zenoh_config import zenoh_config


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def router() -> Iterator[str]:
    """An in-process Zenoh router listening on a free loopback port; yields its endpoint."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    session = zenoh.open(zenoh_config("router", listen=(endpoint,)))
    try:
        yield endpoint
    finally:
        session.close()
