"""``randt security init DIR``: certificates, passwords and Zenoh configs of a secured deployment.

A thin shell over :func:`randt.wire.zenoh_security.write_deployment` (``docs/security.md`` is the recipe).
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer


def security_init(
    directory: Annotated[Path, typer.Argument(help="Directory to write into (created; must be empty).")],
    vehicle: Annotated[
        list[str],
        typer.Option("--vehicle", help="Vehicle id let in, repeatable (its user name and cert CN)."),
    ],
    host: Annotated[
        list[str] | None,
        typer.Option(
            help="Name or address vehicles dial the service by, repeatable [default: localhost, 127.0.0.1]"
        ),
    ] = None,
    mtls: Annotated[bool, typer.Option(help="Require each vehicle's certificate too (mutual TLS).")] = True,
    days: Annotated[int, typer.Option(min=1, help="Days the certificates are valid.")] = 365,
) -> None:
    """Write a CA, certificates, passwords and the service's, a router's and each vehicle's Zenoh config.

    Then: randt serve --listen tls/0.0.0.0:7447 --zenoh-config DIR/service.json5, and on each
    vehicle: randt replay ... --connect tls/HOST:7447 --zenoh-config DIR/vehicle-ID.json5 (copy
    only that vehicle's files to it: ca.pem, ID.pem, ID.key, vehicle-ID.json5).
    """
    from randt.wire.zenoh_security import write_deployment

    if directory.exists() and any(directory.iterdir()):
        raise ValueError(f"{directory} is not empty: randt security init writes into a fresh directory")
    d = write_deployment(directory, vehicle, hosts=host or ("localhost", "127.0.0.1"), mtls=mtls, days=days)
    typer.echo(
        f"wrote {d.directory}: service.json5, router.json5, service-client.json5, "
        f"{', '.join(f'vehicle-{v}.json5' for v in d.vehicles)}, certificates, passwords.txt"
    )
