"""`calibkit triangulate`: 3D markers per frame from a recording's unlabelled blobs.

The handler checks the options and reads the capture; the run is
calibkit/commands/triangulate_run.py."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from calibkit.core.errors import UserError


def register(app: typer.Typer) -> None:
    @app.command("triangulate")
    def triangulate(
        out: Annotated[Path, typer.Option("--out", help="Points CSV to write.")],
        rig_path: Annotated[Path | None, typer.Option(
            "--rig", help="The calibrated rig (--sim: optional; without it the simulated "
                          "cameras' true poses and lenses, a perfect calibration).")] = None,
        src: Annotated[Path | None, typer.Option(
            "--from", help="Recording (.mcrec), plain CSV or DLTdv xypts file.")] = None,
        json_path: Annotated[Path | None, typer.Option("--json", help="Write the figures.")]
        = None,
        epipolar_px: Annotated[float | None, typer.Option(
            "--epipolar-px", help="How far a match may lie from the epipolar line (px). "
                                  "Default: 2, or more as the rig's residual asks.")] = None,
        max_reproj_px: Annotated[float | None, typer.Option(
            "--max-reproj-px", help="Reject markers whose rays miss by more (px). Default: "
                                    "1.5, or more as the rig's residual asks.")] = None,
        min_cameras: Annotated[int, typer.Option(
            "--min-cameras", help="Cameras a new marker needs (3 rules out chance pairs).")]
        = 3,
        two_camera: Annotated[bool, typer.Option(
            "--two-camera/--no-two-camera",
            help="Also accept unambiguous two-camera matches.")] = True,
        residual_px: Annotated[float | None, typer.Option(
            "--residual-px", help="The rig's reprojection residual (px) the gates follow, "
                                  "instead of the rig file's figure or the data's.")] = None,
        estimate_residual: Annotated[bool, typer.Option(
            "--estimate-residual", help="Measure the residual on the data's confident "
                                        "matches even if the rig file records one.")] = False,
        fixed_gates: Annotated[bool, typer.Option(
            "--fixed-gates", help="Gates of fixed size (the defaults or the values given), "
                                  "whatever the rig's residual.")] = False,
        sim: Annotated[bool, typer.Option(
            "--sim", help="Instead of --from: rigid bodies moving through a simulated rig "
                          "(--sim-rig, else a ring of --cameras around --volume), seen with "
                          "--noise-px noise and --ghosts stray blobs; points scored against "
                          "the simulator's truth.")] = False,
        sim_rig: Annotated[Path | None, typer.Option(
            "--sim-rig", help="--sim: the simulated hardware, a true rig (calibkit sim "
                              "rig).")] = None,
        cameras: Annotated[int, typer.Option(help="--sim without --sim-rig: cameras.")] = 6,
        volume: Annotated[float, typer.Option(
            help="--sim without --sim-rig: metres across the volume.")] = 4.0,
        frames: Annotated[int, typer.Option(help="--sim: frames to simulate.")] = 200,
        bodies: Annotated[int, typer.Option(help="--sim: rigid bodies (4 markers each).")]
        = 3,
        noise_px: Annotated[float, typer.Option(
            "--noise-px", help="--sim: centroid noise sigma, px.")] = 0.2,
        ghosts: Annotated[float, typer.Option(
            help="--sim: stray blobs per camera per frame.")] = 0.5,
        seed: Annotated[int, typer.Option(help="--sim: random seed.")] = 0,
    ) -> None:
        """Match unlabelled blobs across cameras and triangulate them, frame by frame.

        The gates follow the rig's reprojection residual (max(default, k x residual), see
        docs/triangulation.md): the figure the rig file's [quality] records, or, for a rig
        file without one, a residual measured on the first frames' confident matches.

        Reads a rig file (--rig) and a capture of unlabelled blobs (--from: a recording, a
        plain CSV, a DLTdv xypts file), or, with --sim, a simulated capture instead.

        CSV columns: frame,x,y,z,reproj_px,ray_mm,n_cameras,cameras (and error_mm when the
        recording carries the simulator's truth)."""
        from calibkit.core.camera import Rig
        from calibkit.core.recording import load_observations

        for name, value in (("--epipolar-px", epipolar_px), ("--max-reproj-px", max_reproj_px)):
            if value is not None and not value > 0:
                raise UserError(f"{name} must be positive, got {value}")
        if min_cameras < 2:
            raise UserError(f"--min-cameras must be at least 2, got {min_cameras}")
        if out.suffix.lower() != ".csv":
            raise UserError(f"--out {out}: points are written as CSV; give a .csv path")
        if sim:
            rig, obs, truth = _sim_capture(src, rig_path, sim_rig, cameras, volume, frames,
                                           bodies, noise_px, ghosts, seed)
        else:
            if rig_path is None or src is None:
                raise UserError("give --rig RIG.toml and --from CAPTURE (a recording, CSV or "
                                "xypts file), or --sim for a simulated capture")
            if out.resolve() == src.resolve():
                raise UserError(f"--out {out} is the input file; give another path")
            rig = Rig.load(rig_path)
            obs, truth = load_observations(src, rig)
        from calibkit.commands.triangulate_run import run_triangulate

        run_triangulate(rig, obs, truth, src, rig_path, out, json_path, epipolar_px,
                        max_reproj_px, min_cameras, two_camera, residual_px,
                        estimate_residual, fixed_gates)

def _sim_capture(src: Path | None, rig_path: Path | None, sim_rig: Path | None, cameras: int,
                 volume: float, frames: int, bodies: int, noise_px: float, ghosts: float,
                 seed: int):
    """--sim: (the rig to triangulate with, the blobs the simulated cameras report, the
    truth for scoring). The rig is --rig (an estimate, checked to be of the same simulated
    cameras) or the hardware itself, said so."""
    from calibkit.core.camera import Rig
    from calibkit.synthetic import sim
    from calibkit.synthetic.runs import check_estimate, sim_hardware

    if src is not None:
        raise UserError("give --from CAPTURE or --sim, not both")
    if noise_px < 0 or ghosts < 0:
        raise UserError("--noise-px and --ghosts must not be negative")
    hardware = sim_hardware(sim_rig, cameras, volume, seed)
    truth, _ = sim.rigid_body_motion(bodies, frames, 100.0,
                                     float(hardware.meta.get("volume_m", volume)), 4, seed)
    obs = sim.observe(hardware, truth, noise_px=noise_px, ghosts_per_camera=ghosts,
                      fps=100.0, seed=seed)
    if rig_path is None:
        typer.echo("no --rig: triangulating with the simulated cameras' true poses and "
                   "lenses (a perfect calibration)", err=True)
        return hardware, obs, truth
    rig = Rig.load(rig_path)
    check_estimate(rig, hardware, rig_path, "--rig")
    return rig, obs, truth
