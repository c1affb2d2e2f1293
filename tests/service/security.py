"""Helpers of the Zenoh security tests: a deployment written by ``randt.wire.zenoh_security`` (the same
generator ``randt security init`` runs), config files, sessions on loopback TLS endpoints."""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import zenoh

from randt.wire.zenoh_config import zenoh_config
from tests.service.conftest import free_port


def tls_endpoint() -> str:
    return f"tls/127.0.0.1:{free_port()}"


def write_config(path: Path, cfg: dict[str, Any]) -> Path:
    path.write_text(json.dumps(cfg, indent=2), encoding="utf-8")
    return path


def open_session(
    config: Path, mode: str, *, listen: tuple[str, ...] = (), connect: tuple[str, ...] = ()
) -> zenoh.Session:
    return zenoh.open(zenoh_config(mode, listen, connect, config_file=config))


def refused(config: Path, endpoint: str) -> str:
    """Open a client session with ``config`` to ``endpoint``; return Zenoh's error, or randt's when
    the config cannot reach the endpoint at all (fails if it opened)."""
    try:
        session = zenoh.open(zenoh_config("client", connect=(endpoint,), config_file=config))
    except (zenoh.ZError, ValueError) as exc:
        return str(exc)
    session.close()
    raise AssertionError(f"a session with {config.name} was let in at {endpoint}")


def wait_for(predicate: Callable[[], bool], timeout: float = 10.0) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.05)
    return predicate()


def linked_identities(session: zenoh.Session) -> list[str | None]:
    """The authenticated identity (certificate CN, else user name) of each link of ``session``."""
    return sorted((link.auth_identifier for link in session.info.links()), key=str)
