"""`calibkit demo`'s run: each step's command run and shown, then the figures against the
simulator's truth.

Apart from calibkit/commands/demo_cmd.py, whose handler reads and checks the options, so
that a handler stays a page of options and a few checks. Like the handler it imports no
library: the steps are the commands themselves, run as child processes.
"""

from __future__ import annotations

import json
import math
import shlex
import subprocess
import sys
import time
from pathlib import Path

import typer

from calibkit.clitools import print_table
from calibkit.core.errors import UserError

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


def _gross(figures: dict) -> int | None:
    """The count of gross errors a figures dict carries, if it carries one (the scorers
    name it `gross...`: poses over 2 cm / 5 deg, points over 10 mm)."""
    for key, value in figures.items():
        if "gross" in key and isinstance(value, (int, float)):
            return int(value)
    return None


def _row(step: str, figure: str, value, figures: dict | None = None) -> list:
    gross = _gross(figures) if figures is not None else None
    return [step, figure, value, "-" if gross is None else gross]


def _intrinsic_rows(intr: dict) -> list[list]:
    """The monitor step's estimate against the truth, worst camera."""
    cams = intr["cameras"]
    return [
        _row("intrinsic", "monitor reprojection RMS, worst camera (px)",
             max(c["rms_px"] for c in cams)),
        _row("intrinsic", "focal length error vs truth, max (%)",
             max(100 * max(abs(c["error"]["fx_rel"]), abs(c["error"]["fy_rel"]))
                 for c in cams)),
        _row("intrinsic", "principal point error vs truth, max (px)",
             max(max(abs(c["error"]["cx_px"]), abs(c["error"]["cy_px"])) for c in cams)),
    ]


def run_demo(out: Path, seed: int, cameras: int, wand_frames: int,
             track_frames: int) -> None:
    """The demo in folder `out` (made): the steps as a user runs them, in order, each
    shown; then the table of figures and what they mean."""
    log = out / "demo.log"
    log.write_text("", encoding="utf-8")
    world = out / "world.truth.toml"
    intr, ext, rig = out / "intrinsics.toml", out / "extrinsic.toml", out / "rig.toml"
    typer.echo(f"calibkit demo: a simulated {cameras}-camera rig; files and full output "
               f"in {out}/\n")
    began = time.monotonic()

    def step(args: list[str], tool: str = "calibkit") -> None:
        _run((CALIBKIT if tool == "calibkit" else MOCAPD) + args,
             f"{tool} " + shlex.join(args), log)

    typer.echo("0. The simulated hardware: a true rig that only the simulator and the "
               "final comparison read")
    step(["sim", "rig", "--cameras", str(cameras), "--seed", str(seed), "--out",
          str(world)])

    typer.echo("1. Each camera's intrinsics from dots shown on a monitor (fast mode: the "
               "dots' imaged centres with capture noise, no rendering)")
    step(["intrinsic", "--sim", "--sim-rig", str(world), "--camera", "all",
          "--no-render", "--seed", str(seed), "--rig", str(intr), "--json",
          str(out / "intrinsic.json")])

    typer.echo("2. Every camera's pose from dots a ceiling projector casts on the floor "
               "and a table, starting from those intrinsics")
    step(["extrinsic", "--projector", "--sim", "--sim-rig", str(world), "--intrinsics",
          str(intr), "--seed", str(seed), "--out", str(ext), "--json",
          str(out / "extrinsic.json")])

    typer.echo("3. Refine every camera (intrinsics too) with a wand waved through the "
               "volume, starting from the projector's poses and dots")
    step(["wand", "--sim", "--sim-rig", str(world), "--rig", str(ext), "--dots",
          str(ext.with_name(ext.stem + ".dots.npz")), "--frames", str(wand_frames),
          "--seed", str(seed), "--out", str(rig), "--json", str(out / "wand.json")])

    typer.echo("4. Compare the calibration with the simulator's true rig")
    step(["compare", str(world), str(rig), "--json", str(out / "compare.json")])

    typer.echo("5. Record a capture of moving rigid bodies and reconstruct its markers")
    step(["sim", "rigid", "--rig", str(world), "--frames", "300", "--bodies", "3",
          "--noise-px", "0.2", "--dropout", "0.05", "--ghosts", "0.5", "--seed",
          str(seed), "--out", str(out / "capture.mcrec")])
    step(["triangulate", "--rig", str(rig), "--from", str(out / "capture.mcrec"),
          "--out", str(out / "points.csv"), "--json", str(out / "points.json")])

    typer.echo("6. Track rigid bodies with mocapd on the calibrated rig: at its start each "
               "body is held still, alone,\n   and defined from the markers mocapd "
               "tracks (as `mocapd rigid-body add --from-live` does; written to\n   "
               f"{out / 'rt' / 'sim-bodies.toml'}), then the bodies move and are tracked")
    step(["start", "--sim", "--rig", str(rig), "--truth-rig", str(world),
          "--frames", str(track_frames), "--fast", "--seed", str(seed),
          "--runtime-dir", str(out / "rt"), "--json", str(out / "track.json")],
         tool="mocapd")

    _report(out, world, intr, rig, began)


def _report(out: Path, world: Path, intr: Path, rig: Path, began: float) -> None:
    """The figures each step's JSON holds, one table; then what was read by whom."""
    intr_fig, ext_fig = _load(out / "intrinsic.json"), _load(out / "extrinsic.json")
    wand, cmp = _load(out / "wand.json"), _load(out / "compare.json")
    pts, track = _load(out / "points.json"), _load(out / "track.json")
    held = wand["held_out"]
    truth = track.get("truth", {})
    ptruth = pts["truth"]
    typer.echo("")
    print_table([
        *_intrinsic_rows(intr_fig),
        _row("extrinsic", "camera position error vs truth, max (mm)",
             ext_fig["truth"]["position_error_max_mm"]),
        _row("wand", "held-out reprojection RMS (px)", held["reprojection_rms_px"], held),
        _row("wand", "held-out wand length error SD (mm)",
             held["wand_length_error_sd_mm"]),
        _row("wand", "grade", wand["grade"]),
        _row("vs truth", "camera position error, max (mm)",
             max(c["position_mm"] for c in cmp["cameras"])),
        _row("vs truth", "camera orientation error, max (deg)",
             max(c["rotation_deg"] for c in cmp["cameras"])),
        _row("vs truth", "3D error over the volume, grid RMS (mm)", cmp["grid_rms_mm"],
             cmp),
        _row("vs truth", "world frame offset (from the tape-measured floor dots, mm)",
             1000.0 * math.hypot(*cmp["alignment"]["translation_m"])),
        _row("capture", "3D points per frame", pts["points_per_frame"]),
        _row("capture", "3D error vs truth, RMS (mm)", ptruth["error_mm_rms"], ptruth),
        _row("capture", "ghost points (fraction)", ptruth["ghost_fraction"]),
        _row("mocapd", "rigid bodies defined live (markers each)",
             ", ".join(str(b["markers"]) for b in
                       track.get("bodies_defined_live", {}).get("bodies", []))),
        _row("mocapd", "body definition error vs truth, worst (mm RMS)",
             max((b["definition_error_mm_rms"] for b in truth.get("bodies", {}).values()
                  if b.get("definition_error_mm_rms") is not None), default=None)),
        _row("mocapd", "frames tracked", track["frames"]),
        _row("mocapd", "latency to poses, median (ms)",
             track["latency_to_poses"]["median_ms"]),
        _row("mocapd", "body position error, RMS (mm)",
             truth.get("position_error_mm_rms"), truth),
        _row("mocapd", "body orientation error, RMS (deg)",
             truth.get("orientation_error_deg_rms"), truth),
        _row("mocapd", "identity swaps", truth.get("body_swaps")),
    ], ["step", "figure", "value", "gross errors"])
    typer.echo(f"\nThe intrinsics came from the monitor step ({intr.name}): every later "
               "step started from that estimate.\n"
               f"The true rig ({world.name}) was read only by the simulator and the "
               "comparisons; the capture and\nmocapd figures are in the true world "
               "frame, so they include the world frame's offset.\nGross errors: poses "
               "off by more than 2 cm or 5 deg, points by more than 10 mm ('-': not "
               "counted by that step).")
    typer.echo(f"demo took {time.monotonic() - began:.0f} s.")
    typer.echo(f"\nNext: `calibkit rig show {rig}`, `calibkit compare --help`, "
               "`mocapd start --help`; docs/simulator.md explains the chain.")
