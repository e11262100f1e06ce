"""The `calibkit` command line: one Typer app; each command lives in calibkit/commands/."""

from __future__ import annotations

import importlib

import typer

from calibkit import __version__
from calibkit.clitools import run_app

app = typer.Typer(
    name="calibkit",
    help="Calibrate a rig of motion-capture cameras (add --sim to any command to use the "
         "built-in simulated rig).",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)

# Each module defines register(app). Order here is the order of `calibkit --help`.
COMMAND_MODULES = (
    "demo_cmd",
    "sim_cmd",
    "detect_cmd",
    "triangulate_cmd",
    "displays_cmd",
    "intrinsic_cmd",
    "extrinsic_cmd",
    "wand_cmd",
    "floor_cmd",
    "rig_cmd",
    "compare_cmd",
    "convert_cmd",
)


def _version(value: bool) -> None:
    if value:
        typer.echo(f"calibkit {__version__}")
        raise typer.Exit()


@app.callback()
def _root(version: bool = typer.Option(False, "--version", callback=_version, is_eager=True,
                                       help="Print the version and exit.")) -> None:
    """calibkit: calibration of multi-camera motion-capture rigs."""


for _name in COMMAND_MODULES:
    try:
        _module = importlib.import_module(f"calibkit.commands.{_name}")
    except ModuleNotFoundError as _exc:  # a command still being written (development only)
        if _exc.name != f"calibkit.commands.{_name}":
            raise
        continue
    _module.register(app)


def main() -> None:
    run_app(app, "calibkit")


if __name__ == "__main__":
    main()
