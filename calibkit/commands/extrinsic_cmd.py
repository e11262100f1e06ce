"""`calibkit extrinsic --projector`: every camera's pose from projected floor and table dots.

The handler checks the options (and writes --template, lights --show-refs); the run is
calibkit/commands/extrinsic_run.py."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from calibkit.clitools import parse_size
from calibkit.core.errors import UserError

if TYPE_CHECKING:
    import numpy as np


def _check_options(out: Path | None, samples: int, shifts: int, step: float, radius: float,
                   ref_sigma_mm: float, height_sigma_mm: float) -> None:
    if out is None:
        raise UserError("--out RIG.toml is required")
    if samples < 1 or shifts < 1 or step <= 0 or radius <= 0:
        raise UserError("--samples and --shifts must be >= 1, --step and --radius > 0")
    if ref_sigma_mm <= 0 or height_sigma_mm <= 0:
        raise UserError("--ref-sigma-mm and --height-sigma-mm must be positive")


def _show_references(pts: np.ndarray, monitor: int, radius: float) -> None:
    """Light the reference dots so the user can mark and measure where they land."""
    from projector.display import WindowDisplay
    from projector.dots import Dots
    from projector.screens import require_display

    require_display()
    window = WindowDisplay(monitor)
    try:
        window.show(Dots.make(pts, radius))
        input(f"{len(pts)} reference dots shown: mark and measure them, then press Enter ")
    finally:
        window.close()


def register(app: typer.Typer) -> None:
    @app.command("extrinsic")
    def extrinsic(
        projector: Annotated[bool, typer.Option(
            "--projector", help="Calibrate from dots a ceiling projector casts on the floor "
                                "and a table (the method there is).")] = False,
        out: Annotated[Path | None, typer.Option(
            "--out", help="The rig file to write (cameras with their poses).")] = None,
        refs_path: Annotated[Path | None, typer.Option(
            "--refs", help="Reference points measured with a tape (TOML, see "
                           "docs/extrinsic.md).")] = None,
        template: Annotated[Path | None, typer.Option(
            "--template", help="Write a reference-points file to fill in (the projector "
                               "pixels of the reference dots) and stop.")] = None,
        show_refs: Annotated[bool, typer.Option(
            "--show-refs", help="Light the reference dots of --refs (or of the template "
                                "layout) on --monitor until Enter, to mark them, and stop.")]
        = False,
        intrinsics: Annotated[Path | None, typer.Option(
            "--intrinsics", help="Rig file with every camera's intrinsics (poses are "
                                 "ignored).")] = None,
        camera: Annotated[list[str] | None, typer.Option(
            "--camera", help="Live: a camera (device number, video, image folder, "
                             "basler:SERIAL, genicam:SERIAL), once per camera of "
                             "--intrinsics, in its order.")] = None,
        monitor: Annotated[int, typer.Option(
            "--monitor", help="Live: the projector's display index.")] = 1,
        projector_size: Annotated[str, typer.Option(
            "--projector-size", help="The projector's resolution (for --template).")]
        = "1280x800",
        table: Annotated[bool | None, typer.Option(
            "--table/--no-table", help="Run the table session (default: when the "
                                       "references have a table).")] = None,
        step: Annotated[float, typer.Option(help="Dot grid step, projector pixels.")] = 64.0,
        shifts: Annotated[int, typer.Option(
            help="The grid is shown SHIFTS x SHIFTS times, offset by step/SHIFTS.")] = 2,
        radius: Annotated[float, typer.Option(help="Dot radius, projector pixels.")] = 8.0,
        samples: Annotated[int, typer.Option(help="Frames averaged per pattern.")] = 3,
        joint: Annotated[bool, typer.Option(
            "--joint/--no-joint", help="Refine all cameras together on the shared dots.")]
        = True,
        ref_sigma_mm: Annotated[float, typer.Option(
            "--ref-sigma-mm", help="How well the reference points were measured.")] = 5.0,
        height_sigma_mm: Annotated[float, typer.Option(
            "--height-sigma-mm", help="How well the table height was measured.")] = 2.0,
        json_path: Annotated[Path | None, typer.Option(
            "--json", help="Write the figures as JSON.")] = None,
        report_path: Annotated[Path | None, typer.Option(
            "--report", help="The report page to write (one self-contained HTML file; "
                             "default NAME.report.html beside the rig file).")] = None,
        sim: Annotated[bool, typer.Option(
            "--sim", help="A simulated projector, table and rig, calibrated from the "
                          "--intrinsics file (calibkit intrinsic --sim); the true rig goes "
                          "to NAME.truth.toml, the simulated tape measurements to "
                          "NAME.refs.toml.")] = False,
        sim_rig: Annotated[Path | None, typer.Option(
            "--sim-rig", help="--sim: the simulated hardware, a true rig (calibkit sim rig); "
                              "default: a ring made from --cameras, --volume, --seed.")]
        = None,
        render: Annotated[bool, typer.Option(
            "--render/--no-render", help="--sim: render every camera frame and detect the "
                                         "dots (slow) instead of projecting them.")] = False,
        cameras: Annotated[int | None, typer.Option(
            "--cameras", help="--sim without --sim-rig: cameras (default: as many as the "
                              "--intrinsics file has).")] = None,
        volume: Annotated[float, typer.Option(
            "--volume", help="--sim: metres across (a --sim-rig file's own volume wins).")]
        = 4.0,
        table_height: Annotated[float, typer.Option(
            "--table-height", help="--sim: table height, metres (0: no table).")] = 0.75,
        size: Annotated[str | None, typer.Option(
            help="--sim without --sim-rig: camera size (default 640x480).")] = None,
        noise_px: Annotated[float, typer.Option(
            "--noise-px", help="--sim (projected dots): centroid noise.")] = 0.2,
        ref_error_mm: Annotated[float, typer.Option(
            "--ref-error-mm", help="--sim: error of the tape measurements.")] = 5.0,
        seed: Annotated[int, typer.Option("--seed", help="--sim: random seed.")] = 0,
    ) -> None:
        """Every camera's pose from projected dots on the floor and a table top."""
        from calibkit.calibrate import extrinsic_pipeline as pipeline
        from calibkit.calibrate.extrinsic_reference import load_references

        if not projector:
            raise UserError("say which method: --projector (dots cast by a ceiling "
                            "projector) is the one there is")
        proj_px = parse_size(projector_size)
        if template is not None:
            n = pipeline.write_template(template, proj_px)
            typer.echo(f"wrote {template}: {n} floor reference dots to measure")
            return
        if show_refs:
            if sim:
                raise UserError("--show-refs lights the real projector: not with --sim")
            refs = load_references(refs_path) if refs_path is not None else None
            _show_references(pipeline.shown_references(refs, proj_px), monitor, radius)
            return
        _check_options(out, samples, shifts, step, radius, ref_sigma_mm, height_sigma_mm)
        from calibkit.commands.extrinsic_run import run_extrinsic

        run_extrinsic(out=out, refs_path=refs_path, intrinsics=intrinsics, camera=camera,
                      monitor=monitor, proj_px=proj_px, table=table, step=step,
                      shifts=shifts, radius=radius, samples=samples, joint=joint,
                      ref_sigma_mm=ref_sigma_mm, height_sigma_mm=height_sigma_mm,
                      json_path=json_path, report_path=report_path, sim=sim,
                      sim_rig=sim_rig, render=render, cameras=cameras, volume=volume,
                      table_height=table_height, size=size, noise_px=noise_px,
                      ref_error_mm=ref_error_mm, seed=seed)
