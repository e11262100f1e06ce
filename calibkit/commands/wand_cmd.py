"""`calibkit wand`: capture a wand dance (live, from a recording, or simulated) and bundle-adjust
the whole rig with it."""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from calibkit.clitools import Progress, parse_floats, parse_view, print_table, write_json
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


def _print_capture(monitor, capture_path: Path) -> None:
    print_table(monitor.rows(), ["camera", "wand samples", "coverage %", "enough"])
    typer.echo("\nimage cells the wand reached (#):\n" + monitor.grid_text() + "\n")
    typer.echo(f"capture saved to {capture_path}")


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
        from calibkit.commands import coverage_view
        from calibkit.core.camera import Rig
        from calibkit.core.easywand import read_easywand_profile
        from calibkit.synthetic.runs import truth_rig_path

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
        extra = pipeline.dots_extra(dots) if dots is not None else None
        initial = Rig.load(rig_path) if rig_path is not None else None
        intr = initial or (Rig.load(intrinsics) if intrinsics is not None else None)
        intr_path = rig_path or intrinsics
        if profile is not None:  # an easyWand camera profile in place of --intrinsics
            if intr is not None or source is None:
                raise UserError("--profile (an easyWand camera profile) goes with --from "
                                "XYPTS.csv, in place of --intrinsics and --rig")
            intr = read_easywand_profile(profile)
        world, run, coverage = None, None, None
        if use_sim:
            from calibkit.synthetic import wand_sim

            run = wand_sim.setup(intr, intr_path, "--rig" if rig_path else "--intrinsics",
                                 sim_rig, cameras, volume, frames, spec.spacing_m, noise_px,
                                 ghosts, seed, with_lframe=dots is None)
            intr, world, batches = run.intrinsics, run.world, run.batches()
            initial = intr if initial is not None else None
        elif camera:
            if intr is None:
                raise UserError("live capture needs --intrinsics RIG.toml (or --rig)")
            batches = pipeline.live_batches(list(camera), intr)
        if intr is None:
            raise UserError("--intrinsics RIG.toml (or --rig) is required")
        if source is not None:
            obs = pipeline.load_capture(source, intr)
        else:
            capture_path = save_capture or out.with_name(out.stem + ".capture.mcrec")
            monitor = pipeline.new_monitor(intr, targets)
            progress = Progress("capture", frames if run else None)
            if view_at is not None:
                coverage = coverage_view.CoverageView(*view_at, monitor)
                typer.echo(f"coverage at {coverage.url}", err=True)
                progress = coverage_view.ViewProgress(progress, coverage, monitor)
            obs, monitor = pipeline.record_capture(
                batches, spec, intr, targets, capture_path, wand_sim.FPS if run else None,
                progress, monitor)
            _print_capture(monitor, capture_path)
        scale_from = None
        if floor_rec is not None:
            world = pipeline.world_from_floor(floor_rec, intr, floor_kind, spec)
            if not length_known and floor_kind == "lframe":  # the L-frame's arms: metres
                floor_obs = pipeline.load_capture(floor_rec, intr)

                def scale_from(rig):
                    from calibkit.calibrate.wand_scale import lframe_scale

                    return lframe_scale(rig, floor_obs)
        views = None
        if refine_intrinsics is not False and monitor_views:
            views = pipeline.monitor_views(intr, intr_path)
            if views is not None:
                typer.echo(f"intrinsics refined with the intrinsic step's {len(views)} "
                           f"monitor dots in {len(views.view_camera)} views")
        from calibkit.calibrate.wand_solve import calibrate

        progress = Progress("wand solve, iterations")
        cal = calibrate(obs, intr, spec.spacing_m, initial, refine_intrinsics, holdout, seed,
                        world, progress=lambda text: progress.update(progress.done + 1, text),
                        extra=extra, target_views=views, length_known=length_known,
                        scale_from=scale_from)
        progress.finish(f"{cal.report['solve']['time_s']:.1f} s in the solver")
        pipeline.write_outputs(cal, out, plots)
        from calibkit.calibrate.html_report import write_wand_report

        write_wand_report(page, cal, out, plots)
        if run is not None:
            run.truth.save(truth_rig_path(out))
        _print(cal.report)
        if json_path is not None:
            write_json(json_path, cal.report)
        typer.echo(f"wrote {out}" + (f" (true rig in {truth_rig_path(out)})" if run else "")
                   + f" and the report {page}")
        if coverage is not None:
            coverage.close()


def _print(report: dict) -> None:
    rows = [[c["name"], c["observations"], round(100 * c["coverage"], 1),
             c["reprojection_rms_px"], c["held_out_rms_px"],
             c.get("position_std_mm", math.nan), c.get("orientation_std_deg", math.nan)]
            for c in report["cameras"]]
    print_table(rows, ["camera", "obs", "coverage_%", "rms_px", "held_out_px", "pos_sd_mm",
                       "rot_sd_deg"])
    s, h = report["solve"], report["held_out"]
    typer.echo("")
    print_table([
        ["reprojection RMS (px)", s["reprojection_rms_px"], h["reprojection_rms_px"]],
        ["wand length variation, SD/mean (%)", s["wand_length_variation_pct"],
         h["wand_length_variation_pct"]],
        ["wand length error, mean (mm)", s["wand_length_error_mean_mm"],
         h["wand_length_error_mean_mm"]],
        ["wand length error, SD (mm)", s["wand_length_error_sd_mm"],
         h["wand_length_error_sd_mm"]],
        ["mean ray distance (mm)", s["mean_ray_distance_mm"], h["mean_ray_distance_mm"]],
        ["frames", s["frames"], h["frames"]],
    ], ["figure", "solved", "held out"])
    for part, figs in (("solved", s), ("held out", h)):
        for key in ("reason", "wand_length_variation_reason"):
            if key in figs:
                typer.echo(f"{part}: not computable: {figs[key]}")
    sy = report.get("systematic") or {}
    typer.echo("")
    print_table([[what, sy.get(f"{key}_mm", math.nan), sy.get(f"{key}_pct", math.nan),
                  sy.get(f"{key}_reason", "")]
                 for key, what in (("volume", "across the volume"),
                                   ("radius", "image centre to edges"),
                                   ("region", "held-out regions"),
                                   ("trend", "trend with position"))],
                ["systematic length error", "mm", "%", "not computable because"])
    typer.echo("")
    for c in report["intrinsics"]["cameras"]:
        typer.echo(f"intrinsics {c['name']}: {c['chosen']} ({c['why']})")
    scale = report["scale"]
    typer.echo(f"\nsolve: {s['iterations']} iterations, {s['time_s']:.1f} s, noise "
               f"{s['noise_px']:.3f} px, {s['outliers']} outliers dropped; world frame: "
               f"{report['world_frame']}; scale: "
               + ("from the " + scale["source"] if scale["known"] else
                  "unknown, " + scale["unit"]))
    det = report.get("position_ppm") or {}
    if det.get("camera") is not None:
        typer.echo(f"least determined camera: {det['camera']}, position SD {det['ppm']:.0f} "
                   "ppm of its distance from the reference camera")
    for w in report["warnings"]:
        typer.echo(f"warning: {w}")
    typer.echo(f"grade: {report['grade']} ({report['grade_reason']})")
