"""The Zenoh configuration every session of ours uses: explicit endpoints, multicast scouting off.

The service (:mod:`randt.service.transport`), the vehicle publisher (:mod:`randt.clients.publisher`), the
tests
and the benchmarks open their Zenoh sessions with :func:`zenoh_config`; settings check their
endpoints with :func:`check_endpoints`. This is the only module of :mod:`wire` that imports Zenoh,
and :mod:`wire` does not import it on its own: ``from randt.wire.zenoh_config import zenoh_config``.

A native Zenoh JSON5 config file (``randt serve --zenoh-config FILE``, ``RANDT_ZENOH_CONFIG``;
``RANDT_VEHICLE_ZENOH_CONFIG`` for vehicles) is the base of the config when given: TLS, mTLS,
user/password, access control, timeouts and anything else Zenoh knows come from it. Three things
always come from randt's own settings and replace the file's values (a warning is logged when the
file said otherwise): ``mode``, ``listen/endpoints`` and ``connect/endpoints`` (one place says
where a service listens, and ``randt serve`` checks those ports before it starts), and multicast
scouting stays **off** (a randt session reaches only the endpoints it is given; gossip scouting
is left to the file). ``docs/security.md`` has the recipe, :mod:`randt.wire.zenoh_security` writes the
files.
"""

from __future__ import annotations

import json
import logging
import re
from pathlib import Path

import zenoh

__all__ = ["ENDPOINT_PATTERN", "check_endpoints", "load_config_file", "zenoh_config"]

log = logging.getLogger(__name__)

#: What an endpoint must look like: ``<protocol>/<address>``, e.g. ``tcp/127.0.0.1:7447``.
ENDPOINT_PATTERN = re.compile(r"^(tcp|udp|quic|tls|ws|unixsock-stream)/\S+$")


def check_endpoints(endpoints: tuple[str, ...] | list[str]) -> tuple[str, ...]:
    """Return ``endpoints`` as a tuple, or raise ValueError naming the first malformed one."""
    for ep in endpoints:
        if not ENDPOINT_PATTERN.match(ep):
            raise ValueError(f"not a Zenoh endpoint (expected e.g. tcp/127.0.0.1:7447): {ep!r}")
    return tuple(endpoints)


def load_config_file(path: Path | str) -> zenoh.Config:
    """Read a native Zenoh JSON5 config file, or raise ValueError naming the file and Zenoh's reason.

    Zenoh checks the file whole when it reads it (unknown keys, missing fields of an ACL rule, bad
    JSON5), so a mistake is reported here, before anything starts.
    """
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"Zenoh config file {str(path)!r} does not exist or is not a file")
    try:
        return zenoh.Config.from_file(str(path))
    except zenoh.ZError as exc:
        reason = str(exc).split(" at /", 1)[0]  # drop the Rust source location
        raise ValueError(f"Zenoh config file {str(path)!r} is not valid: {reason}") from exc


def _get(cfg: zenoh.Config, key: str) -> object:
    return json.loads(cfg.get_json(key))


def check_protocols(cfg: zenoh.Config, endpoints: tuple[str, ...], source: Path | str) -> None:
    """Raise ValueError naming the first endpoint whose protocol the config's
    ``transport/link/protocols`` leaves out (e.g. ``tcp/...`` with ``randt security init``'s
    TLS-only config), instead of Zenoh's failure when the session opens."""
    allowed = _get(cfg, "transport/link/protocols")
    if not isinstance(allowed, list):
        return
    for ep in endpoints:
        proto = ep.split("/", 1)[0]
        if proto not in allowed:
            address = ep.split("/", 1)[1] if "/" in ep else ""
            hint = f" (e.g. {allowed[0]}/{address})" if allowed else ""
            listed = ", ".join(map(str, allowed)) or "none"
            raise ValueError(
                f"endpoint {ep} uses {proto}, which Zenoh config file {str(source)!r} does not allow "
                f"(transport.link.protocols: {listed}): use one of those{hint}"
            )


def zenoh_config(
    mode: str,
    listen: tuple[str, ...] = (),
    connect: tuple[str, ...] = (),
    *,
    config_file: Path | str | None = None,
) -> zenoh.Config:
    """A Zenoh config for ``mode`` (``client``, ``peer`` or ``router``) with explicit endpoints.

    Multicast scouting is off: a session reaches only the endpoints it is given (and, in peer mode,
    whoever connects to its ``listen`` endpoints). With ``config_file`` the file is the base and
    ``mode``, ``listen`` and ``connect`` replace its values (module docstring), even when empty.
    """
    if mode not in ("client", "peer", "router"):
        raise ValueError(f"Zenoh mode must be client, peer or router, got {mode!r}")
    listen, connect = check_endpoints(listen), check_endpoints(connect)
    if config_file is None:
        cfg = zenoh.Config()
    else:
        cfg = load_config_file(config_file)
        default = zenoh.Config()
        ours: dict[str, object] = {
            "mode": mode,
            "listen/endpoints": list(listen),
            "connect/endpoints": list(connect),
            "scouting/multicast/enabled": False,
        }
        for key, value in ours.items():
            theirs = _get(cfg, key)
            if theirs != _get(default, key) and theirs != value:
                log.warning(
                    "Zenoh config file %s sets %s to %s; randt uses %s (set it with randt's own "
                    "options: docs/security.md)",
                    config_file, key, json.dumps(theirs), json.dumps(value),
                )  # fmt: skip
        check_protocols(cfg, listen + connect, config_file)
        # explicit, even when empty: a peer listens on tcp/[::]:0 (every interface) by default
        cfg.insert_json5("listen/endpoints", json.dumps(list(listen)))
        cfg.insert_json5("connect/endpoints", json.dumps(list(connect)))
    cfg.insert_json5("mode", json.dumps(mode))
    cfg.insert_json5("scouting/multicast/enabled", "false")
    if listen:
        cfg.insert_json5("listen/endpoints", json.dumps(list(listen)))
    if connect:
        cfg.insert_json5("connect/endpoints", json.dumps(list(connect)))
    return cfg
