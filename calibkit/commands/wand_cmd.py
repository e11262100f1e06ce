"""`calibkit wand`: capture a wand dance (live, from a recording, or simulated) and bundle-adjust
the whole rig with it.

The handler checks the options; the run is calibkit/commands/wand_run.py."""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from calibkit.clitools import parse_floats, parse_view
from calibkit.core.errors import UserError

if TYPE_CHECKING:
    from calibkit.calibrate.wand import WandSpec


def _check_sources(source: Path | None, use_sim: bool, camera: list[str] | None,
                   intrinsics: Path | None, rig_path: Path | None, dots: Path | None,
                   floor_rec: Path | None) -> None:
    if sum([source is not None, use_sim, bool(camera)]) != 1:
        raise UserError("give exactly one of --from REC, --sim or --camera (live)")
    if intrinsics is not None and rig_path is not None:
        raise UserError("give --intrinsics or --rig, not both")
    if dots is not None and rig_path is None:
        raise UserError("--dots needs --rig: the poses from the calibkit extrinsic run that "
                        "wrote the dots (they are in the same world frame)")
    if dots is not None and floor_rec is not None:
        raise UserError("give --dots or --floor, not both: each sets the world frame")


def _wand_spec(spacing: str, wand_length: str | None) -> tuple[WandSpec, bool]:
    """The wand from --spacing and --wand-length, and whether its length is known."""
    from calibkit.calibrate.wand import WandSpec

    spec = WandSpec(tuple(parse_floats(spacing, "--spacing")))
    if wand_length is None:
        return spec, True
    if wand_length.strip().lower() == "unknown":
        if spec.n_markers < 2:
            raise UserError("--wand-length unknown needs a wand of 2 or 3 markers (--spacing)")
        return spec, False
    try:
        length_m = float(wand_length)
    except ValueError:
        raise UserError(f"--wand-length takes metres or 'unknown', got {wand_length!r}") \
            from None
    if not (math.isfinite(length_m) and length_m > 0) or spec.n_markers < 2:
        raise UserError("--wand-length must be a positive length in metres between the ends "
                        f"of a wand of 2 or 3 markers, got {wand_length!r}")
    s = spec.spacing_m
    return WandSpec(tuple((v - s[0]) * length_m / spec.length_m for v in s)), True


def register(app: typer.Typer) -> None:
    @app.command("wand")
    def wand(
        out: Annotated[Path, typer.Option("--out", help="The calibrated rig file to write.")],
        source: Annotated[Path | None, typer.Option(
            "--from", help="A recording (.mcrec) or plain CSV of the wand dance.")] = None,
        profile: Annotated[Path | None, typer.Option(
            "--profile", help="An easyWand camera profile: the intrinsics for a DLTdv/easyWand "
                              "xypts file given to --from (docs/easywand.md).")] = None,
        use_sim: Annotated[bool, typer.Option(
            "--sim", help="Simulate a rig and a wand dance, calibrated from the --intrinsics "
                          "or --rig file (calibkit intrinsic / extrinsic --sim); the true "
                          "rig goes to NAME.truth.toml.")] = False,
        sim_rig: Annotated[Path | None, typer.Option(
            "--sim-rig", help="--sim: the simulated hardware, a true rig (calibkit sim rig); "
                              "default: a ring made from --cameras, --volume, --seed.")]
        = None,
        camera: Annotated[list[str] | None, typer.Option(
            "--camera", help="Live: a camera (device number, video, image folder, "
                             "basler:SERIAL, genicam:SERIAL), once per camera of "
                             "--intrinsics, in its order.")] = None,
        intrinsics: Annotated[Path | None, typer.Option(
            "--intrinsics", help="Rig file whose intrinsics are used (poses ignored).")] = None,
        rig_path: Annotated[Path | None, typer.Option(
            "--rig", help="Rig file with intrinsics and initial poses (e.g. from "
                          "calibkit extrinsic).")] = None,
        dots: Annotated[Path | None, typer.Option(
            "--dots", help="Projector dots on the floor and table (NAME.dots.npz from "
                           "calibkit extrinsic): solved with the wand, they hold the world "
                           "frame; needs --rig from the same extrinsic run.")] = None,
        spacing: Annotated[str, typer.Option(
            "--spacing", help="Marker positions along the wand, metres.")] = "0,0.2,0.5",
        wand_length: Annotated[str | None, typer.Option(
            "--wand-length", help="Metres between the wand's end markers (--spacing is then "
                                  "scaled to it), or 'unknown': the rig is solved "
                                  "scale-free, in units of --spacing, and the report says "
                                  "so.")] = None,
        refine_intrinsics: Annotated[bool | None, typer.Option(
            "--refine-intrinsics/--fix-intrinsics",
            help="Refine the intrinsics with the poses (held near the intrinsic step's "
                 "estimate by its uncertainty), or keep them as given. Default: refined when "
                 "the file gives their uncertainty or views; intrinsics without them are "
                 "kept unless refining measurably fits the capture better (per camera, "
                 "docs/wand.md).", show_default=False)] = None,
        monitor_views: Annotated[bool, typer.Option(
            "--monitor-views/--no-monitor-views",
            help="When refining the intrinsics, solve with the intrinsic step's monitor "
                 "views (the NAME.views.npz its rig file names), or with priors from its "
                 "standard deviations only.")] = True,
        holdout: Annotated[float, typer.Option(
            "--holdout", help="Share of wand frames kept out of the solve to check it.")] = 0.1,
        floor_rec: Annotated[Path | None, typer.Option(
            "--floor", help="A recording of the L-frame (or wand) on the floor: sets the "
                            "world frame.")] = None,
        floor_kind: Annotated[str, typer.Option(
            "--floor-kind", help="What --floor holds: lframe, wand or plane.")] = "lframe",
        min_samples: Annotated[int, typer.Option(
            "--min-samples", help="Capture: wand sightings each camera needs.")] = 1000,
        min_coverage: Annotated[float, typer.Option(
            "--min-coverage", help="Capture: share of image cells each camera needs.")] = 0.8,
        save_capture: Annotated[Path | None, typer.Option(
            "--save-capture", help="Where the capture's recording goes (live and --sim; "
                                   "default NAME.capture.mcrec).")] = None,
        json_path: Annotated[Path | None, typer.Option(
            "--json", help="Write the figures as JSON.")] = None,
        plots: Annotated[bool, typer.Option(
            "--plots/--no-plots", help="Write NAME.layout.png and NAME.residuals.png.")] = True,
        view: Annotated[str | None, typer.Option(
            "--view", help="Live and --sim: show each camera's coverage filling in on a web "
                           "page at [HOST:]PORT (a bare port: this computer only).")]
        = None,
        report_path: Annotated[Path | None, typer.Option(
            "--report", help="The report page to write (one self-contained HTML file; "
                             "default NAME.report.html beside the rig file).")] = None,
        cameras: Annotated[int | None, typer.Option(
            "--cameras", help="--sim without --sim-rig: cameras (default: as many as the "
                              "--intrinsics/--rig file has).")] = None,
        frames: Annotated[int, typer.Option("--frames", help="--sim: wand frames.")] = 3000,
        noise_px: Annotated[float, typer.Option("--noise-px", help="--sim: noise.")] = 0.1,
        ghosts: Annotated[float, typer.Option(
            "--ghosts", help="--sim: stray blobs per camera per frame.")] = 0.0,
        volume: Annotated[float, typer.Option(
            "--volume", help="--sim: metres across (a --sim-rig file's own volume wins).")]
        = 4.0,
        seed: Annotated[int, typer.Option("--seed", help="Random seed.")] = 0,
    ) -> None:
        """Calibrate every camera at once from a wand waved through the volume."""
        from calibkit.calibrate import wand_pipeline as pipeline

        spec, length_known = _wand_spec(spacing, wand_length)
        if not 0 <= holdout < 0.9:
            raise UserError(f"--holdout must be in [0, 0.9), got {holdout}")
        targets = pipeline.CaptureTargets(min_samples, min_coverage)
        _check_sources(source, use_sim, camera, intrinsics, rig_path, dots, floor_rec)
        if view is not None and source is not None:
            raise UserError("--view shows a capture's coverage as it fills; --from reads a "
                            "recording that is already made")
        view_at = parse_view(view) if view is not None else None
        page = report_path or out.with_name(out.stem + ".report.html")
        if not page.resolve().parent.is_dir():
            raise UserError(f"--report: the folder {page.parent} does not exist")
        from calibkit.commands.wand_run import run_wand

        run_wand(out=out, source=source, profile=profile, use_sim=use_sim, sim_rig=sim_rig,
                 camera=camera, intrinsics=intrinsics, rig_path=rig_path, dots=dots,
                 spec=spec, length_known=length_known, refine_intrinsics=refine_intrinsics,
                 monitor_views=monitor_views, holdout=holdout, floor_rec=floor_rec,
                 floor_kind=floor_kind, targets=targets, save_capture=save_capture,
                 json_path=json_path, plots=plots, view_at=view_at, page=page,
                 cameras=cameras, frames=frames, noise_px=noise_px, ghosts=ghosts,
                 volume=volume, seed=seed)
