"""The `calibkit` command line: one Typer app; each command lives in calibkit/commands/."""

from __future__ import annotations

from calibkit import __version__
from calibkit.clitools import build_app, run_app

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

app = build_app("calibkit", "Calibrate a rig of motion-capture cameras (add --sim to any "
                "command to use the built-in simulated rig).", __version__,
                "calibkit.commands", COMMAND_MODULES)


def main() -> None:
    run_app(app, "calibkit")


if __name__ == "__main__":
    main()
