"""`calibkit demo`: the whole chain on the simulated rig, with no hardware.

It runs the very commands a user runs, prints each one before its result, and ends with
the figures that matter against the simulator's truth: so the demo is also the tutorial.
calibkit never imports the daemon; mocapd runs as a separate process, as in real use.
The handler checks the options; the run is calibkit/commands/demo_run.py.
"""

from __future__ import annotations

import tempfile
from pathlib import Path
from typing import Annotated

import typer

from calibkit.core.errors import UserError


def register(app: typer.Typer) -> None:
    @app.command("demo")
    def demo(
        out: Annotated[Path | None, typer.Option(
            "--out", help="Folder for the files it makes (default: a new folder under the "
                          "system's temporary folder, named when the demo starts).")] = None,
        seed: Annotated[int, typer.Option("--seed", help="Random seed.")] = 0,
        cameras: Annotated[int, typer.Option("--cameras", help="Simulated cameras.")] = 6,
        wand_frames: Annotated[int, typer.Option(
            "--wand-frames", help="Frames of wand dance to calibrate from.")] = 1500,
        track_frames: Annotated[int, typer.Option(
            "--track-frames", help="Frames to track with the calibrated rig.")] = 480,
    ) -> None:
        """The whole calibration chain on a simulated rig, as a user runs it: intrinsics
        from a monitor, poses from a projector, then a wand; check the result against the
        simulator's truth, reconstruct a capture with it, then track rigid bodies with
        mocapd and score the poses.

        Reads nothing: every step runs on the simulator (each is a --sim command)."""
        if cameras < 3 or wand_frames < 200 or track_frames < 10:
            raise UserError("the demo needs --cameras >= 3, --wand-frames >= 200 and "
                            "--track-frames >= 10")
        if out is None:  # never the current folder: a clone is not the place for its files
            out = Path(tempfile.mkdtemp(prefix="calibkit-demo-"))
        out.mkdir(parents=True, exist_ok=True)
        from calibkit.commands.demo_run import run_demo

        run_demo(out, seed, cameras, wand_frames, track_frames)
