"""The ``randt`` typer app: its options, its commands (one module per group) and ``main()``."""

from __future__ import annotations

import logging
import sys
from typing import Annotated

import typer

from cli import fleet, mapping, register, serve, tiles
from cli.errors import exits_on_error

app = typer.Typer(
    name="randt",
    help="randt-fleet: RANDT scan matching and fleet map building.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)
tiles_app = typer.Typer(
    help="Sessions, trajectories and map tiles from a running service, over HTTP.",
    no_args_is_help=True,
)

#: Every command, in ``randt --help``'s order: (typer app, name, function). Each is wrapped by
#: :func:`cli.errors.exits_on_error` here, so no command maps its own errors.
COMMANDS = (
    (app, "register", register.register),
    (app, "demo-register", register.demo_register),
    (app, "map", mapping.map_sequence),
    (app, "eval", mapping.eval_trajectory),
    (app, "serve", serve.serve),
    (app, "replay", fleet.replay),
    (app, "simulate", fleet.simulate),
    (app, "demo", fleet.demo),
    (app, "config", register.show_config),
    (tiles_app, "sessions", tiles.tiles_sessions),
    (tiles_app, "trajectory", tiles.tiles_trajectory),
    (tiles_app, "maps", tiles.tiles_maps),
    (tiles_app, "list", tiles.tiles_list),
    (tiles_app, "download", tiles.tiles_download),
    (tiles_app, "export", tiles.tiles_export),
)
for _app, _name, _command in COMMANDS:
    _full = _name if _app is app else f"tiles {_name}"
    _app.command(_name)(exits_on_error(_command, _full))
app.add_typer(tiles_app, name="tiles")


@app.callback()
def _main(
    verbose: Annotated[bool, typer.Option("--verbose", "-v", help="Log debug messages.")] = False,
) -> None:
    logging.basicConfig(
        level=logging.DEBUG if verbose else logging.WARNING,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )


def main() -> None:
    """Console-script entry point."""
    app()


if __name__ == "__main__":
    main()
