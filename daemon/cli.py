"""The `mocapd` command line: one Typer app; each command lives in daemon/commands/."""

from __future__ import annotations

from calibkit import __version__
from calibkit.clitools import build_app, run_app

# Each module defines register(app). Order here is the order of `mocapd --help`.
COMMAND_MODULES = (
    "start_cmd",
    "control_cmd",
    "rigid_cmd",
    "unit_cmd",
    "kernels_cmd",
    "markerset_cmd",
    "evaluate_cmd",
    "track_cmd",
    "view_cmd",
    "node_cmd",
)

app = build_app("mocapd", "Track markers and rigid bodies with a calibrated rig and serve "
                "their poses over UDP, serial lines, NatNet and VRPN.", __version__,
                "daemon.commands", COMMAND_MODULES)


def main() -> None:
    run_app(app, "mocapd")


if __name__ == "__main__":
    main()
