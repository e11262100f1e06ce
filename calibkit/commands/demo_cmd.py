"""`calibkit demo`: the whole chain on the simulated rig, with no hardware.

It runs the very commands a user runs, prints each one before its result, and ends with
the figures that matter against the simulator's truth: so the demo is also the tutorial.
calibkit never imports the daemon; mocapd runs as a separate process, as in real use.
"""

from __future__ import annotations

import json
import shlex
import subprocess
import sys
import time
from pathlib import Path
from typing import Annotated

import typer

from calibkit.clitools import print_table
from calibkit.errors import UserError

CALIBKIT = [sys.executable, "-m", "calibkit.cli"]
MOCAPD = [sys.executable, "-m", "daemon.cli"]


def _run(argv: list[str], shown: str, log: Path) -> None:
    """Run one step; its output goes to the log; a failure ends the demo with its message."""
    typer.echo(f"$ {shown}")
    start = time.monotonic()
    with open(log, "a", encoding="utf-8") as handle:
        handle.write(f"$ {shown}\n")
        handle.flush()
        proc = subprocess.run(argv, stdout=handle, stderr=subprocess.PIPE, text=True,
                              check=False)
        handle.write(proc.stderr)
    if proc.returncode != 0:
        last = (proc.stderr.strip().splitlines() or ["(no message)"])[-1]
        raise UserError(f"demo step failed: {shown}: {last} (full output in {log})")
    typer.echo(f"  done in {time.monotonic() - start:.1f} s")


def _load(path: Path) -> dict:
    return json.loads(path.read_text(encoding="utf-8"))


def register(app: typer.Typer) -> None:
    @app.command("demo")
    def demo(
        out: Annotated[Path, typer.Option("--out", help="Folder for the files it makes.")]
        = Path("calibkit-demo"),
        seed: Annotated[int, typer.Option("--seed", help="Random seed.")] = 0,
        cameras: Annotated[int, typer.Option("--cameras", help="Simulated cameras.")] = 6,
        wand_frames: Annotated[int, typer.Option(
            "--wand-frames", help="Frames of wand dance to calibrate from.")] = 1500,
        track_frames: Annotated[int, typer.Option(
            "--track-frames", help="Frames to track with the calibrated rig.")] = 480,
    ) -> None:
        """Calibrate a simulated rig with a wand, check it against the truth, reconstruct a
        capture with it, then track rigid bodies with mocapd and score the poses."""
        if cameras < 3 or wand_frames < 200 or track_frames < 10:
            raise UserError("the demo needs --cameras >= 3, --wand-frames >= 200 and "
                            "--track-frames >= 10")
        out.mkdir(parents=True, exist_ok=True)
        log = out / "demo.log"
        log.write_text("", encoding="utf-8")
        rig, truth_rig = out / "rig.toml", out / "rig.truth.toml"
        typer.echo(f"calibkit demo: a simulated {cameras}-camera rig; files and full output "
                   f"in {out}/\n")

        typer.echo("1. Calibrate every camera from a wand waved through the volume")
        args = ["wand", "--sim", "--cameras", str(cameras), "--frames", str(wand_frames),
                "--seed", str(seed), "--out", str(rig), "--json", str(out / "wand.json")]
        _run(CALIBKIT + args, "calibkit " + shlex.join(args), log)

        typer.echo("2. Compare the calibration with the simulator's true rig")
        args = ["compare", str(truth_rig), str(rig), "--json", str(out / "compare.json")]
        _run(CALIBKIT + args, "calibkit " + shlex.join(args), log)

        typer.echo("3. Record a capture of moving rigid bodies and reconstruct its markers")
        args = ["sim", "rigid", "--rig", str(truth_rig), "--frames", "300", "--bodies", "3",
                "--noise-px", "0.2", "--dropout", "0.05", "--ghosts", "0.5", "--seed",
                str(seed), "--out", str(out / "capture.mcrec")]
        _run(CALIBKIT + args, "calibkit " + shlex.join(args), log)
        args = ["triangulate", "--rig", str(rig), "--from", str(out / "capture.mcrec"),
                "--out", str(out / "points.csv"), "--json", str(out / "points.json")]
        _run(CALIBKIT + args, "calibkit " + shlex.join(args), log)

        typer.echo("4. Track rigid bodies live with mocapd on the calibrated rig")
        args = ["start", "--sim", "--rig", str(rig), "--truth-rig", str(truth_rig),
                "--frames", str(track_frames), "--fast", "--seed", str(seed),
                "--json", str(out / "track.json")]
        _run(MOCAPD + args, "mocapd " + shlex.join(args), log)

        wand, cmp = _load(out / "wand.json"), _load(out / "compare.json")
        pts, track = _load(out / "points.json"), _load(out / "track.json")
        held = wand["held_out"]
        truth = track.get("truth", {})
        typer.echo("")
        print_table([
            ["wand", "held-out reprojection RMS (px)", held["reprojection_rms_px"]],
            ["wand", "held-out wand length error SD (mm)", held["wand_length_error_sd_mm"]],
            ["wand", "grade", wand["grade"]],
            ["vs truth", "camera position error, max (mm)",
             max(c["position_mm"] for c in cmp["cameras"])],
            ["vs truth", "camera orientation error, max (deg)",
             max(c["rotation_deg"] for c in cmp["cameras"])],
            ["vs truth", "3D error over the volume, grid RMS (mm)", cmp["grid_rms_mm"]],
            ["capture", "3D points per frame", pts["points_per_frame"]],
            ["capture", "3D error vs truth, RMS (mm)", pts["truth"]["error_mm_rms"]],
            ["capture", "ghost points (fraction)", pts["truth"]["ghost_fraction"]],
            ["mocapd", "frames tracked", track["frames"]],
            ["mocapd", "latency to poses, median (ms)", track["latency_to_poses"]["median_ms"]],
            ["mocapd", "body position error, RMS (mm)", truth.get("position_error_mm_rms")],
            ["mocapd", "body orientation error, RMS (deg)",
             truth.get("orientation_error_deg_rms")],
            ["mocapd", "identity swaps", truth.get("body_swaps")],
        ], ["step", "figure", "value"])
        typer.echo(f"\nNext: `calibkit rig show {rig}`, `calibkit compare --help`, "
                   "`mocapd start --help`; docs/ explains each step.")
