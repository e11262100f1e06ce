"""The `mocapd` command line."""

from __future__ import annotations

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


def _version(value: bool) -> None:
    if value:
        typer.echo(f"mocapd {__version__}")
        raise typer.Exit()


@app.callback()
def _root(version: bool = typer.Option(False, "--version", callback=_version, is_eager=True,
                                       help="Print the version and exit.")) -> None:
    """mocapd: the motion-capture tracking daemon."""


def main() -> None:
    run_app(app, "mocapd")


if __name__ == "__main__":
    main()
