"""`calibkit sim`: write a simulated rig, or a simulated capture with its ground truth."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from calibkit.clitools import HELP_MARKUP, load_rig_option, parse_floats, parse_size
from calibkit.core.errors import UserError


def _distortions() -> dict[str, tuple[float, ...]]:
    """--distortion's choices: lens profiles measured on real cameras (calibkit.core.camera,
    imported here so that `calibkit sim --help` loads no numpy)."""
    from calibkit.core.camera import WEBCAM_DIST, BASLER_658x492_DIST

    return {"none": (0.0, 0.0, 0.0, 0.0, 0.0), "webcam": WEBCAM_DIST,
            "basler": BASLER_658x492_DIST}


sim_app = typer.Typer(help="Simulated rigs and captures with ground truth.",
                      no_args_is_help=True, rich_markup_mode=HELP_MARKUP)

Out = Annotated[Path, typer.Option("--out", help="Recording (.mcrec) or plain CSV (.csv).")]
RigOpt = Annotated[Path | None, typer.Option(
    "--rig", help="The true rig (calibkit sim rig); without it a ring of --cameras cameras is "
                  "made and written beside the output as NAME.rig.toml.")]
Cameras = Annotated[int, typer.Option("--cameras", help="Cameras, when no --rig is given.")]
Volume = Annotated[float, typer.Option("--volume", help="Volume across (m), when no --rig.")]
Frames = Annotated[int, typer.Option("--frames", help="Frames to simulate.")]
Fps = Annotated[float, typer.Option("--fps", help="Frame rate, Hz.")]
Noise = Annotated[float, typer.Option("--noise-px", help="Centroid noise sigma; 0 = exact.")]
Dropout = Annotated[float, typer.Option("--dropout", help="Chance a marker is hidden.")]
Ghosts = Annotated[float, typer.Option("--ghosts", help="Stray blobs per camera per frame.")]
Seed = Annotated[int, typer.Option("--seed", help="Random seed: same seed, same data.")]
Unsync = Annotated[float, typer.Option(
    "--unsync-ms", help="Cameras not in sync: each camera's clock is offset by a random "
                        "amount up to this (ms); 0 = triggered cameras.")]
Jitter = Annotated[float, typer.Option(
    "--jitter-ms", help="Random jitter (sigma, ms) of each frame's capture time.")]


def _scene_rig(rig: Path | None, cameras: int, volume: float, out: Path, seed: int):
    """The rig a scene is seen by: the given one, or a new ring saved beside the output."""
    from calibkit.synthetic import sim

    if rig is not None:
        return load_rig_option(rig)
    made = sim.make_rig(cameras, volume, seed=seed)
    rig_out = out.with_name(out.stem + ".rig.toml")
    made.save(rig_out)
    typer.echo(f"wrote {rig_out}: {cameras} cameras around a {volume:g} m volume")
    return made


def _volume(rig) -> float:
    return float(rig.meta.get("volume_m", 4.0))


def _write(out: Path, rig, truth, noise, dropout, ghosts, fps, seed, unsync_ms=0.0,
           jitter_ms=0.0) -> None:
    """Observe the scene and write it, with the truth inside a recording and, for scripts,
    always beside it as NAME.truth.csv."""
    import numpy as np

    from calibkit.core.recording import save_observations, save_truth_csv, truth_path_for
    from calibkit.synthetic import sim

    if unsync_ms < 0 or jitter_ms < 0:
        raise UserError("--unsync-ms and --jitter-ms must not be negative")
    offsets = np.random.default_rng(seed + 7).uniform(0.0, unsync_ms * 1e6, len(rig))
    obs = sim.observe(rig, truth, noise_px=noise, dropout=dropout, ghosts_per_camera=ghosts,
                      fps=fps, seed=seed, clock_offset_ns=offsets, jitter_ns=jitter_ms * 1e6)
    save_observations(out, obs, truth, rig)
    if out.suffix.lower() != ".csv":
        save_truth_csv(truth_path_for(out), truth)
    typer.echo(f"wrote {out}: {len(obs.frames())} frames, {len(obs)} blobs from "
               f"{len(rig)} cameras (truth in {truth_path_for(out)})")


@sim_app.command("rig")
def sim_rig(
    out: Annotated[Path, typer.Option("--out", help="The rig file to write.")],
    cameras: Annotated[int, typer.Option("--cameras", help="Number of cameras (2-32).")] = 6,
    volume: Annotated[float, typer.Option("--volume", help="Volume across, metres.")] = 4.0,
    size: Annotated[str, typer.Option("--size", help="Image size WIDTHxHEIGHT.")] = "640x480",
    fov: Annotated[float, typer.Option("--fov", help="Horizontal field of view, deg.")] = 70.0,
    distortion: Annotated[str, typer.Option(
        "--distortion", help="Lens: none, webcam or basler.")] = "webcam",
    seed: Seed = 0,
) -> None:
    """Write a true rig: cameras on a ring around a capture volume.

    Reads nothing but its options: it is the simulator."""
    from calibkit.synthetic import sim

    distortions = _distortions()
    if distortion not in distortions:
        raise UserError(f"--distortion must be one of {', '.join(distortions)}, got "
                        f"{distortion!r}")
    rig = sim.make_rig(cameras, volume, parse_size(size), fov, distortions[distortion], seed)
    rig.save(out)
    typer.echo(f"wrote {out}: {len(rig)} cameras around a {volume:g} m volume")


@sim_app.command("static")
def sim_static(out: Out, rig: RigOpt = None, markers: Annotated[int, typer.Option(
        "--markers", help="Number of markers.")] = 20, frames: Frames = 100, fps: Fps = 100.0,
        noise_px: Noise = 0.2, dropout: Dropout = 0.0, ghosts: Ghosts = 0.0,
        seed: Seed = 0, cameras: Cameras = 6, volume: Volume = 4.0, unsync_ms: Unsync = 0.0,
        jitter_ms: Jitter = 0.0) -> None:
    """Markers standing still in the volume.

    Reads nothing but its options and a true rig (--rig): it is the simulator."""
    from calibkit.synthetic import sim

    true_rig = _scene_rig(rig, cameras, volume, out, seed)
    truth = sim.static_markers(markers, frames, _volume(true_rig), seed)
    _write(out, true_rig, truth, noise_px, dropout, ghosts, fps, seed, unsync_ms, jitter_ms)


@sim_app.command("wand")
def sim_wand(out: Out, rig: RigOpt = None, frames: Frames = 3000, fps: Fps = 100.0,
             spacing: Annotated[str, typer.Option(
                 "--spacing", help="Marker positions along the wand, metres.")] = "0,0.2,0.5",
             noise_px: Noise = 0.1, dropout: Dropout = 0.0, ghosts: Ghosts = 0.0,
             seed: Seed = 0, cameras: Cameras = 6, volume: Volume = 4.0,
             unsync_ms: Unsync = 0.0, jitter_ms: Jitter = 0.0) -> None:
    """A wand waved through the volume.

    Reads nothing but its options and a true rig (--rig): it is the simulator."""
    from calibkit.synthetic import sim

    true_rig = _scene_rig(rig, cameras, volume, out, seed)
    truth = sim.wand_motion(frames, fps, _volume(true_rig),
                            parse_floats(spacing, "--spacing"), seed)
    _write(out, true_rig, truth, noise_px, dropout, ghosts, fps, seed, unsync_ms, jitter_ms)


@sim_app.command("rigid")
def sim_rigid(out: Out, rig: RigOpt = None, bodies: Annotated[int, typer.Option(
        "--bodies", help="Number of rigid bodies.")] = 3, markers: Annotated[int, typer.Option(
        "--markers", help="Markers per body (3-8).")] = 4, frames: Frames = 500,
        fps: Fps = 100.0, noise_px: Noise = 0.2, dropout: Dropout = 0.0, ghosts: Ghosts = 0.0,
        seed: Seed = 0, cameras: Cameras = 6, volume: Volume = 4.0, unsync_ms: Unsync = 0.0,
        jitter_ms: Jitter = 0.0) -> None:
    """Rigid bodies moving through the volume.

    Reads nothing but its options and a true rig (--rig): it is the simulator."""
    from calibkit.synthetic import sim

    true_rig = _scene_rig(rig, cameras, volume, out, seed)
    truth, _ = sim.rigid_body_motion(bodies, frames, fps, _volume(true_rig), markers, seed)
    _write(out, true_rig, truth, noise_px, dropout, ghosts, fps, seed, unsync_ms, jitter_ms)


def register(app: typer.Typer) -> None:
    app.add_typer(sim_app, name="sim")
