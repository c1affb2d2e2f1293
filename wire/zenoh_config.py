"""The Zenoh configuration every session of ours uses: explicit endpoints, multicast scouting off.

The service (:mod:`service.transport`), the vehicle publisher (:mod:`clients.publisher`), the tests
and the benchmarks open their Zenoh sessions with :func:`zenoh_config`; settings check their
endpoints with :func:`check_endpoints`. This is the only module of :mod:`wire` that imports Zenoh,
and :mod:`wire` does not import it on its own: ``from wire.zenoh_config import zenoh_config``.
"""

from __future__ import annotations

import json
import re

import zenoh

__all__ = ["ENDPOINT_PATTERN", "check_endpoints", "zenoh_config"]

#: What an endpoint must look like: ``<protocol>/<address>``, e.g. ``tcp/127.0.0.1:7447``.
ENDPOINT_PATTERN = re.compile(r"^(tcp|udp|quic|tls|ws|unixsock-stream)/\S+$")


def check_endpoints(endpoints: tuple[str, ...] | list[str]) -> tuple[str, ...]:
    """Return ``endpoints`` as a tuple, or raise ValueError naming the first malformed one."""
    for ep in endpoints:
        if not ENDPOINT_PATTERN.match(ep):
            raise ValueError(f"not a Zenoh endpoint (expected e.g. tcp/127.0.0.1:7447): {ep!r}")
    return tuple(endpoints)


def zenoh_config(mode: str, listen: tuple[str, ...] = (), connect: tuple[str, ...] = ()) -> zenoh.Config:
    """A Zenoh config for ``mode`` (``client``, ``peer`` or ``router``) with explicit endpoints.

    Multicast scouting is off: a session reaches only the endpoints it is given (and, in peer mode,
    whoever connects to its ``listen`` endpoints).
    """
    if mode not in ("client", "peer", "router"):
        raise ValueError(f"Zenoh mode must be client, peer or router, got {mode!r}")
    cfg = zenoh.Config()
    cfg.insert_json5("mode", json.dumps(mode))
    cfg.insert_json5("scouting/multicast/enabled", "false")
    if listen:
        cfg.insert_json5("listen/endpoints", json.dumps(list(check_endpoints(listen))))
    if connect:
        cfg.insert_json5("connect/endpoints", json.dumps(list(check_endpoints(connect))))
    return cfg
