"""`calibkit demo`: the whole chain on the simulated rig, step by step, with no hardware."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import numpy as np
import typer

from calibkit import sim
from calibkit.clitools import print_table
from calibkit.correspondence import match_frames
from calibkit.observations import Observations, Truth
from calibkit.recording import save_observations


def _truth_error_mm(points, truth: Truth) -> float:
    """RMS distance from each reconstructed point to the nearest true marker of its frame."""
    errors = []
    for f in np.unique(points.frame):
        _, xyz = truth.at_frame(f)
        p = points.xyz[points.frame == f]
        d = np.linalg.norm(p[:, None, :] - xyz[None, :, :], axis=2).min(axis=1)
        errors.append(d)
    e = np.concatenate(errors) if errors else np.zeros(0)
    return float(np.sqrt(np.mean(e**2)) * 1000) if len(e) else float("nan")


def register(app: typer.Typer) -> None:
    @app.command("demo")
    def demo(
        out: Annotated[Path, typer.Option("--out", help="Folder for the files it makes.")]
        = Path("calibkit-demo"),
        seed: Annotated[int, typer.Option("--seed", help="Random seed.")] = 0,
        frames: Annotated[int, typer.Option("--frames", help="Frames to capture.")] = 200,
    ) -> None:
        """Simulate a 6-camera rig, record a capture, reconstruct it, and print what it made."""
        out.mkdir(parents=True, exist_ok=True)
        # 1. the rig
        rig = sim.make_rig(6, 4.0, seed=seed)
        rig.save(out / "rig.toml")
        # 2. a capture: three rigid bodies and a few static markers, 0.3 px noise
        bodies_truth, bodies = sim.rigid_body_motion(3, frames, 100.0, 4.0, 4, seed)
        static = sim.static_markers(5, frames, 4.0, seed + 1)
        truth = Truth(np.concatenate([bodies_truth.frame, static.frame]),
                      np.concatenate([bodies_truth.marker, static.marker + 100]),
                      np.concatenate([bodies_truth.xyz, static.xyz]))
        obs: Observations = sim.observe(rig, truth, noise_px=0.3, dropout=0.05,
                                        ghosts_per_camera=0.5, seed=seed)
        save_observations(out / "capture.mcrec", obs, truth, rig)
        # 3. reconstruct the markers from the unlabelled blobs
        points = match_frames(rig, obs)
        typer.echo(f"calibkit demo: files in {out}/ (rig.toml, capture.mcrec)\n")
        rows = []
        for i, cam in enumerate(rig):
            mine = obs.camera == i
            c = cam.centre
            rows.append([cam.name, f"{cam.width}x{cam.height}", round(cam.fx, 1),
                         f"({c[0]:.2f}, {c[1]:.2f}, {c[2]:.2f})",
                         round(float(np.sum(mine)) / frames, 1),
                         int(np.sum(mine & (obs.marker < 0)))])
        print_table(rows, ["camera", "size", "f_px", "centre_m", "blobs/frame", "ghosts"])
        n_markers = len(np.unique(truth.marker))
        typer.echo("")
        print_table([
            ["frames", frames], ["markers (3 bodies + 5 static)", n_markers],
            ["blobs recorded", len(obs)],
            ["3D points reconstructed per frame", round(len(points.frame) / frames, 2)],
            ["3D error vs truth (mm RMS)", round(_truth_error_mm(points, truth), 3)],
            ["reprojection error (px, median)", round(float(np.median(points.reproj_px)), 3)],
        ], ["what", "value"])
