"""``randt serve``: the fleet mapping service (Zenoh ingest and HTTP) in the foreground.

Before anything starts (no store lock, no matcher process), the HTTP port, the Zenoh listen
endpoints and the data directory are checked: a busy one is one line and its exit code.
"""

from __future__ import annotations

import errno
import logging
import socket
from enum import StrEnum
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer

from randt.cli.errors import PortInUseError

if TYPE_CHECKING:
    from randt.service.settings import ServiceSettings

#: The options of ``randt serve`` that override the ``ServiceSettings`` field of the same name.
SETTINGS_OPTIONS = (
    "data_dir", "zenoh_mode", "listen", "connect", "zenoh_config", "http_host", "http_port", "executor",
    "ray_address",
)  # fmt: skip


#: ``--ros2-connect``'s help: its default is :class:`randt.service.settings.Ros2Settings`' (written
#: out here, so that ``--help`` does not import the settings; tests/service/test_ros2.py checks it).
ROS2_CONNECT_HELP = (
    "With --ros2: the robots' rmw_zenohd router, repeatable  [default: the --connect endpoints "
    "(and --zenoh-config), else tcp/127.0.0.1:7447; env var: RANDT_ROS2__CONNECT (a JSON list)]"
)


class ZenohMode(StrEnum):
    peer = "peer"
    client = "client"


class Executor(StrEnum):
    local = "local"
    ray = "ray"


def serve(
    data_dir: Annotated[Path | None, typer.Option(help="Data directory.")] = None,
    zenoh_mode: Annotated[ZenohMode | None, typer.Option(help="Zenoh mode.")] = None,
    listen: Annotated[list[str] | None, typer.Option(help="Zenoh endpoint to listen on, repeatable.")] = None,
    connect: Annotated[
        list[str] | None, typer.Option(help="Zenoh endpoint to connect to, repeatable.")
    ] = None,
    zenoh_config: Annotated[
        Path | None,
        typer.Option(
            help="Native Zenoh JSON5 config file: TLS, passwords, access control (docs/security.md)."
        ),
    ] = None,
    http_host: Annotated[str | None, typer.Option(help="HTTP bind address.")] = None,
    http_port: Annotated[int | None, typer.Option(help="HTTP port.")] = None,
    executor: Annotated[
        Executor | None,
        typer.Option(
            help="Where the matchers run: local worker processes, or Ray actors across a Ray cluster "
            '(pip install "randt-fleet[ray]"; docs/deploy.md).'
        ),
    ] = None,
    ray_address: Annotated[
        str | None, typer.Option(help="With --executor ray: the Ray cluster to join (none: a local Ray).")
    ] = None,
    ros2: Annotated[
        bool,
        typer.Option(
            "--ros2",
            help="Also take ROS 2 robots' PointCloud2 topics on rmw_zenoh and answer them with Odometry "
            '(pip install "randt-fleet[ros2]"; RANDT_ROS2__*; docs/ros2.md).',
        ),
    ] = False,
    ros2_connect: Annotated[
        list[str] | None,
        typer.Option(help=ROS2_CONNECT_HELP),
    ] = None,
) -> None:
    """Run the fleet mapping service (Zenoh ingest + HTTP) until SIGTERM or Ctrl-C.

    Every option is also an environment variable (shown with its default); the other settings
    (queue sizes, matcher processes, admission, tokens) are environment variables only:
    randt config lists them all.
    """
    import uvicorn

    from randt.service.app import create_app
    from randt.service.georef import check_map_origin
    from randt.service.settings import ServiceSettings
    from randt.service.store import check_data_dir_free

    overrides: dict[str, Any] = {
        "data_dir": data_dir,
        "zenoh_mode": zenoh_mode.value if zenoh_mode else None,
        "listen": tuple(listen) if listen else None,
        "connect": tuple(connect) if connect else None,
        "zenoh_config": zenoh_config,
        "http_host": http_host,
        "http_port": http_port,
        "executor": executor.value if executor else None,
        "ray_address": ray_address,
    }
    settings = ServiceSettings(**{k: v for k, v in overrides.items() if v is not None})
    if ros2 or ros2_connect:
        settings = with_ros2(settings, ros2_connect)
    check_ports_free(settings)
    check_data_dir_free(settings.data_dir)
    check_map_origin(settings.data_dir, settings.default_map, settings.map_origin)
    logging.getLogger().setLevel(logging.INFO)
    app_ = create_app(settings)
    typer.echo(
        f"randt serve: zenoh {settings.zenoh_mode} listen {list(settings.listen)} connect "
        f"{list(settings.connect)}"
        f"{f' config {settings.zenoh_config}' if settings.zenoh_config else ''}; "
        f"http://{settings.http_host}:{settings.http_port}; "
        f"matchers {settings.executor}{f' at {settings.ray_address}' if settings.ray_address else ''}; "
        f"data {settings.data_dir}{ros2_line(settings)}",
        err=True,
    )
    uvicorn.run(app_, host=settings.http_host, port=settings.http_port, log_level="info")


def ros2_line(settings: ServiceSettings) -> str:
    r = settings.ros2
    return f"; ROS 2 domain {r.domain} via {list(r.routers)}, topics {list(r.topics)}" if r.enabled else ""


def with_ros2(settings: ServiceSettings, connect: list[str] | None) -> ServiceSettings:
    """``settings`` with the ROS 2 bridge on, and its router when given (else the one the settings
    name: ``RANDT_ROS2__CONNECT``, or the service's own ``connect``), checked: the ``ros2`` extra
    must be installed (one line naming it, before anything starts)."""
    from randt.service.settings import Ros2Settings
    from randt.wire.ros2 import typestore

    typestore()  # FormatError naming the extra, without rosbags
    ros2 = settings.ros2.model_dump()
    ros2["enabled"] = True
    if connect:
        ros2["connect"] = tuple(connect)
        if "zenoh_config" in settings.ros2.from_service:  # (the service's file, for its own router)
            ros2["zenoh_config"] = None
    return settings.model_copy(update={"ros2": Ros2Settings(**ros2)})


def check_ports_free(settings: ServiceSettings) -> None:
    """Raise :class:`PortInUseError` if the HTTP port or a Zenoh listen endpoint is taken.

    Each is bound for a moment as the servers bind it (``SO_REUSEADDR``, so a port in TIME_WAIT is
    free, a listening one is not). Endpoints that are not tcp/udp/quic ``host:port`` are left to Zenoh.
    """
    http = f"{settings.http_host}:{settings.http_port}"
    busy = f"HTTP port {http} is in use (another service?): choose another with --http-port"
    _check_bind("tcp", settings.http_host, settings.http_port, busy)
    for endpoint in settings.listen:
        proto, _, address = endpoint.partition("/")
        host, _, port = address.split("#")[0].rpartition(":")
        if proto not in ("tcp", "udp", "quic", "tls", "ws") or not port.isdigit() or not host:
            continue
        _check_bind(
            "udp" if proto in ("udp", "quic") else "tcp",
            host.strip("[]"),
            int(port),
            f"Zenoh endpoint {endpoint} is in use (another service or router?): choose another with --listen",
        )


def _check_bind(proto: str, host: str, port: int, busy: str) -> None:
    if port == 0:
        return
    kind = socket.SOCK_DGRAM if proto == "udp" else socket.SOCK_STREAM
    try:
        family, _, _, _, address = socket.getaddrinfo(host, port, type=kind)[0]
    except socket.gaierror as exc:
        raise ValueError(f"cannot listen on {host}:{port}: {exc.strerror}") from exc
    with socket.socket(family, kind) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind(address)
            if kind == socket.SOCK_STREAM:
                s.listen()
        except OSError as exc:
            if exc.errno == errno.EADDRINUSE:
                raise PortInUseError(busy) from exc
            raise ValueError(f"cannot listen on {host}:{port}: {exc.strerror}") from exc
