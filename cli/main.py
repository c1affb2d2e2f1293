"""The ``randt`` typer app: its options, its commands (one module per group) and ``main()``."""

from __future__ import annotations

import logging
import sys
from typing import Annotated

import typer
from typer.core import TyperCommand

from randt.cli import config, fleet, interrupt, mapping, register, security, serve, tiles
from randt.cli.errors import ExitCode, exit_code_table, exits_on_error

# Plain help (rich_markup_mode=None): click's layout, no "<bool>" type column, text as written.
app = typer.Typer(
    name="randt",
    help="randt-fleet: RANDT scan matching and fleet map building.",
    epilog="\b\nExit codes (every command; errors are one line 'randt: error: ...' on stderr):\n"
    + exit_code_table(),
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
    rich_markup_mode=None,
)
security_app = typer.Typer(
    help="Zenoh security: TLS certificates, passwords and access control (docs/security.md).",
    no_args_is_help=True,
    rich_markup_mode=None,
)
tiles_app = typer.Typer(
    help="Sessions, trajectories and map tiles from a running service, over HTTP.",
    no_args_is_help=True,
    rich_markup_mode=None,
)

_SERVICE = config.settings_command("randt.service.settings:ServiceSettings", serve.SETTINGS_OPTIONS)
_PUBLISHER = config.settings_command("randt.clients.publisher:PublisherSettings", fleet.PUBLISHER_OPTIONS)

#: Every command, in ``randt --help``'s order: (typer app, name, function, command class). Each is
#: wrapped by :func:`randt.cli.errors.exits_on_error` here, so no command maps its own errors.
COMMANDS: tuple[tuple[typer.Typer, str, object, type[TyperCommand] | None], ...] = (
    (app, "register", register.register, None),
    (app, "demo-register", register.demo_register, None),
    (app, "map", mapping.map_sequence, None),
    (app, "eval", mapping.eval_trajectory, None),
    (app, "serve", serve.serve, _SERVICE),
    (app, "replay", fleet.replay, _PUBLISHER),
    (app, "simulate", fleet.simulate, _PUBLISHER),
    (app, "demo", fleet.demo, None),
    (app, "config", config.show_config, None),
    (security_app, "init", security.security_init, None),
    (tiles_app, "sessions", tiles.tiles_sessions, None),
    (tiles_app, "trajectory", tiles.tiles_trajectory, None),
    (tiles_app, "maps", tiles.tiles_maps, None),
    (tiles_app, "list", tiles.tiles_list, None),
    (tiles_app, "download", tiles.tiles_download, None),
    (tiles_app, "export", tiles.tiles_export, None),
)
for _app, _name, _command, _cls in COMMANDS:
    _full = _name if _app is app else f"{'security' if _app is security_app else 'tiles'} {_name}"
    _app.command(_name, cls=_cls)(exits_on_error(_command, _full))  # type: ignore[arg-type]
app.add_typer(tiles_app, name="tiles")
app.add_typer(security_app, name="security")


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
    interrupt.install()
    try:
        app()
    except SystemExit as exc:
        if exc.code == ExitCode.INTERRUPTED:  # (Typer's own for a Ctrl-C outside a command: no word)
            interrupt.say("randt: interrupted")
        raise
    except Exception as exc:
        if not interrupt.explains(exc):  # (a Ctrl-C wrapped in another error ends as one too)
            raise
        interrupt.say("randt: interrupted")
        raise SystemExit(ExitCode.INTERRUPTED) from None


if __name__ == "__main__":
    main()
