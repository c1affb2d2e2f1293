"""``randt serve``: the fleet mapping service (Zenoh ingest and HTTP) in the foreground."""

from __future__ import annotations

import logging
from enum import StrEnum
from pathlib import Path
from typing import Annotated

import typer


class ZenohMode(StrEnum):
    peer = "peer"
    client = "client"


def serve(
    data_dir: Annotated[Path | None, typer.Option(help="Data directory [env RANDT_DATA_DIR].")] = None,
    zenoh_mode: Annotated[ZenohMode | None, typer.Option(help="Zenoh mode [env RANDT_ZENOH_MODE].")] = None,
    listen: Annotated[
        list[str] | None, typer.Option(help="Zenoh endpoint to listen on, repeatable [env RANDT_LISTEN].")
    ] = None,
    connect: Annotated[
        list[str] | None, typer.Option(help="Zenoh endpoint to connect to, repeatable [env RANDT_CONNECT].")
    ] = None,
    http_host: Annotated[str | None, typer.Option(help="HTTP bind address [env RANDT_HTTP_HOST].")] = None,
    http_port: Annotated[int | None, typer.Option(help="HTTP port [env RANDT_HTTP_PORT].")] = None,
) -> None:
    """Run the fleet mapping service (Zenoh ingest + HTTP) until SIGTERM or Ctrl-C."""
    import uvicorn

    from service.app import create_app
    from service.settings import ServiceSettings

    overrides = {
        "data_dir": data_dir,
        "zenoh_mode": zenoh_mode.value if zenoh_mode else None,
        "listen": tuple(listen) if listen else None,
        "connect": tuple(connect) if connect else None,
        "http_host": http_host,
        "http_port": http_port,
    }
    settings = ServiceSettings(**{k: v for k, v in overrides.items() if v is not None})
    logging.getLogger().setLevel(logging.INFO)
    app_ = create_app(settings)
    typer.echo(
        f"randt serve: zenoh {settings.zenoh_mode} listen {list(settings.listen)} connect "
        f"{list(settings.connect)}; http://{settings.http_host}:{settings.http_port}; "
        f"data {settings.data_dir}",
        err=True,
    )
    uvicorn.run(app_, host=settings.http_host, port=settings.http_port, log_level="info")
