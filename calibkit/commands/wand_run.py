"""`calibkit wand`'s run: the intrinsics and initial poses read, the wand dance captured
(live, simulated) or read, the world frame, the solve, its files and its figures.

Apart from calibkit/commands/wand_cmd.py, whose handler reads and checks the options, so
that a handler stays a page of options and a few checks.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING

import typer

from calibkit.clitools import Progress, print_table, write_json
from calibkit.core.errors import UserError

if TYPE_CHECKING:
    from calibkit.calibrate.wand import WandSpec
    from calibkit.calibrate.wand_pipeline import CaptureTargets


def run_wand(*, out: Path, source: Path | None, profile: Path | None, use_sim: bool,
             sim_rig: Path | None, camera: list[str] | None, intrinsics: Path | None,
             rig_path: Path | None, dots: Path | None, spec: WandSpec, length_known: bool,
             refine_intrinsics: bool | None, monitor_views: bool, holdout: float,
             floor_rec: Path | None, floor_kind: str, targets: CaptureTargets,
             save_capture: Path | None, json_path: Path | None, plots: bool,
             view_at: tuple | None, page: Path, cameras: int | None, frames: int,
             noise_px: float, ghosts: float, volume: float, seed: int) -> None:
    """`calibkit wand`'s run once its options are checked: the rig files read, the capture
    made or read, the world frame, the solve, the rig, plots and report written, the
    figures said."""
    from calibkit.calibrate import wand_pipeline as pipeline
    from calibkit.commands import coverage_view
    from calibkit.core.camera import Rig
    from calibkit.core.easywand import read_easywand_profile
    from calibkit.synthetic.runs import truth_rig_path

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


def _print_capture(monitor, capture_path: Path) -> None:
    print_table(monitor.rows(), ["camera", "wand samples", "coverage %", "enough"])
    typer.echo("\nimage cells the wand reached (#):\n" + monitor.grid_text() + "\n")
    typer.echo(f"capture saved to {capture_path}")

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
