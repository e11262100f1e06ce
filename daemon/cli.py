"""The `mocapd` command line: one Typer app; each command lives in daemon/commands/."""

from __future__ import annotations

import importlib

import typer

from calibkit import __version__
from calibkit.clitools import run_app

app = typer.Typer(
    name="mocapd",
    help="Track markers and rigid bodies with a calibrated rig and serve their poses over "
         "UDP and serial lines.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)

# Each module defines register(app). Order here is the order of `mocapd --help`.
COMMAND_MODULES = (
    "start_cmd",
    "control_cmd",
    "rigid_cmd",
    "unit_cmd",
    "markerset_cmd",
)


def _version(value: bool) -> None:
    if value:
        typer.echo(f"mocapd {__version__}")
        raise typer.Exit()


@app.callback()
def _root(version: bool = typer.Option(False, "--version", callback=_version, is_eager=True,
                                       help="Print the version and exit.")) -> None:
    """mocapd: the motion-capture tracking daemon."""


for _name in COMMAND_MODULES:
    try:
        _module = importlib.import_module(f"daemon.commands.{_name}")
    except ModuleNotFoundError as _exc:  # a command still being written (development only)
        if _exc.name != f"daemon.commands.{_name}":
            raise
        continue
    _module.register(app)


def main() -> None:
    run_app(app, "mocapd")


if __name__ == "__main__":
    main()
