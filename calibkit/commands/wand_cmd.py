"""`calibkit wand`: capture a wand dance (live, from a recording, or simulated) and bundle-adjust
the whole rig with it."""

from __future__ import annotations

import math
from collections.abc import Iterator
from pathlib import Path
from typing import Annotated

import numpy as np
import typer

from calibkit import floor
from calibkit.camera import Rig
from calibkit.clitools import Progress, print_table, write_json
from calibkit.commands.common import (
    check_estimate,
    need_intrinsics_for_sim,
    parse_floats,
    sim_hardware,
    truth_rig_path,
)
from calibkit.errors import UserError
from calibkit.observations import Observations, Truth
from calibkit.recording import RecordingWriter, load_observations
from calibkit.synthetic import sim
from calibkit.wand import CaptureMonitor, WandSpec, identify

CHUNK_FRAMES = 50  # simulated frames handed to the capture loop at a time


def capture(batches: Iterator[Observations], spec: WandSpec, intrinsics: Rig,
            monitor: CaptureMonitor, writer: RecordingWriter | None,
            progress: Progress) -> Observations | None:
    """Feed batches of frames through identification until every camera has enough (or
    Ctrl-C); every batch is appended to the recording as it comes. Returns what it got."""
    parts: list[Observations] = []
    frames = 0
    try:
        for batch in batches:
            if len(batch):
                parts.append(batch)
                monitor.add(identify(batch, spec, intrinsics))
                if writer is not None:
                    writer.append_observations(batch)
            frames += len(np.unique(batch.frame)) if len(batch) else 1
            progress.update(frames, monitor.summary())
            if monitor.done():
                break
    except KeyboardInterrupt:
        progress.finish("interrupted: using what was captured")
        return Observations.concatenate(parts) if parts else None
    progress.finish(monitor.summary())
    return Observations.concatenate(parts) if parts else None


def _sim_batches(obs: Observations) -> Iterator[Observations]:
    frames = obs.frames()
    for i in range(0, len(frames), CHUNK_FRAMES):
        lo, hi = frames[i], frames[min(i + CHUNK_FRAMES, len(frames)) - 1]
        yield obs.select((obs.frame >= lo) & (obs.frame <= hi))


def _live_batches(specs: list[str], rig: Rig) -> Iterator[Observations]:
    """One frame from every camera at a time, detected: cameras named as in the rig, in the
    order given."""
    from calibkit.detect import DetectorConfig, detect
    from calibkit.sources import open_source

    if len(specs) != len(rig):
        raise UserError(f"give one --camera per camera of the intrinsics file ({len(rig)}), "
                        f"got {len(specs)}")
    sources = [open_source(s) for s in specs]
    config = DetectorConfig()
    try:
        for index, frames in enumerate(zip(*sources, strict=False)):
            rows = []
            for c, frame in enumerate(frames):
                blobs = detect(frame.image, config)
                n = len(blobs.uv)
                rows.append(Observations(rig.names, [cam.size for cam in rig],
                                         np.full(n, index), np.full(n, c),
                                         np.full(n, frame.t_ns), blobs.uv, blobs.area,
                                         blobs.peak))
            yield Observations.concatenate(rows)
    finally:
        for s in sources:
            s.close()


def _lframe_obs(rig: Rig, lframe: floor.LFrame, seed: int, noise_px: float) -> Observations:
    """A simulated L-frame lying on the true floor at the origin, 30 frames."""
    pts = lframe.points((0.0, 0.0), 0.0)
    n = 30
    truth = Truth(np.repeat(np.arange(n), 3), np.tile(np.arange(3), n), np.tile(pts, (n, 1)))
    return sim.observe(rig, truth, noise_px=noise_px, seed=seed + 17)


def register(app: typer.Typer) -> None:
    @app.command("wand")
    def wand(
        out: Annotated[Path, typer.Option("--out", help="The calibrated rig file to write.")],
        source: Annotated[Path | None, typer.Option(
            "--from", help="A recording (.mcrec) or plain CSV of the wand dance.")] = None,
        use_sim: Annotated[bool, typer.Option(
            "--sim", help="Simulate a rig and a wand dance, calibrated from the --intrinsics "
                          "or --rig file (calibkit intrinsic / extrinsic --sim); the true "
                          "rig goes to NAME.truth.toml.")] = False,
        sim_rig: Annotated[Path | None, typer.Option(
            "--sim-rig", help="--sim: the simulated hardware, a true rig (calibkit sim rig); "
                              "default: a ring made from --cameras, --volume, --seed.")]
        = None,
        camera: Annotated[list[str] | None, typer.Option(
            "--camera", help="Live: a camera device number or video, once per camera of "
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
        refine_intrinsics: Annotated[bool, typer.Option(
            "--refine-intrinsics/--fix-intrinsics",
            help="Refine the intrinsics with the poses (held near the intrinsic step's "
                 "estimate by its uncertainty), or keep them as given.")] = True,
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
        spec = WandSpec(tuple(parse_floats(spacing, "--spacing")))
        if not 0 <= holdout < 0.9:
            raise UserError(f"--holdout must be in [0, 0.9), got {holdout}")
        if min_samples < 1 or not 0 <= min_coverage <= 1:
            raise UserError("--min-samples must be >= 1 and --min-coverage in [0, 1]")
        modes = sum([source is not None, use_sim, bool(camera)])
        if modes != 1:
            raise UserError("give exactly one of --from REC, --sim or --camera (live)")
        if intrinsics is not None and rig_path is not None:
            raise UserError("give --intrinsics or --rig, not both")
        if dots is not None and rig_path is None:
            raise UserError("--dots needs --rig: the poses from the calibkit extrinsic run that "
                            "wrote the dots (they are in the same world frame)")
        if dots is not None and floor_rec is not None:
            raise UserError("give --dots or --floor, not both: each sets the world frame")
        extra = None
        if dots is not None:
            from calibkit.extrinsic import bundle_data, load_dots

            dot_obs = load_dots(dots)

            def extra(start_rig):
                # On their planes only: the dots' positions come from a homography fitted to
                # tape measurements (mm errors) and priors on them pull the wand's scale and
                # shape; the planes alone kept the rig 2.7x closer to the truth (docs/wand.md).
                return bundle_data(start_rig, dot_obs, known=False)
        initial = Rig.load(rig_path) if rig_path is not None else None
        intr = initial or (Rig.load(intrinsics) if intrinsics is not None else None)
        capture_path = save_capture or out.with_name(out.stem + ".capture.mcrec")
        world = None
        if use_sim:
            if intr is None:
                raise need_intrinsics_for_sim("calibkit wand")
            if sim_rig is not None and cameras is not None:
                raise UserError("give --sim-rig or --cameras, not both: the rig file sets the "
                                "cameras")
            # without --sim-rig: the ring `calibkit intrinsic --sim` made with the same
            # options, whose image size the estimate file records
            true_rig = sim_hardware(sim_rig, cameras or len(intr), volume, seed,
                                    intr.cameras[0].size)
            check_estimate(intr, true_rig, rig_path or intrinsics,
                           "--rig" if rig_path is not None else "--intrinsics")
            # the cameras as the hardware numbers them, as a live capture's --camera order
            intr = Rig(tuple(intr[n] for n in true_rig.names), intr.quality, intr.meta)
            if initial is not None:
                initial = intr
            volume = float(true_rig.meta.get("volume_m", volume))
            truth = sim.wand_motion(frames, 100.0, volume, spec.spacing_m, seed)
            obs_all = sim.observe(true_rig, truth, noise_px=noise_px, ghosts_per_camera=ghosts,
                                  seed=seed)
            if dots is None:  # else the projector's dots hold the world frame
                floor_obs = _lframe_obs(true_rig, floor.LFrame(), seed, noise_px)

                def world(r, _xyz):  # the L-frame lies at the true origin: truth's frame
                    return floor.world_from_recording(r, floor_obs, "lframe")
            batches: Iterator[Observations] = _sim_batches(obs_all)
        elif camera:
            if intr is None:
                raise UserError("live capture needs --intrinsics RIG.toml (or --rig)")
            batches = _live_batches(list(camera), intr)
        if intr is None:
            raise UserError("--intrinsics RIG.toml (or --rig) is required")
        if source is not None:
            obs, _ = load_observations(source, intr)
        else:
            monitor = CaptureMonitor(intr.names, [c.size for c in intr], min_samples,
                                     min_coverage)
            total = frames if use_sim else None
            with RecordingWriter(capture_path, intr.names, [c.size for c in intr],
                                 100.0 if use_sim else None) as writer:
                obs = capture(batches, spec, intr, monitor, writer, Progress("capture", total))
            if obs is None:
                raise UserError("nothing was captured")
            print_table(monitor.rows(), ["camera", "wand samples", "coverage %", "enough"])
            typer.echo("\nimage cells the wand reached (#):\n" + monitor.grid_text() + "\n")
            typer.echo(f"capture saved to {capture_path}")
        if floor_rec is not None:
            floor_obs_rec, _ = load_observations(floor_rec, intr)

            def world(r, _xyz):
                return floor.world_from_recording(r, floor_obs_rec, floor_kind,
                                                  spacing_m=spec.spacing_m)
        from calibkit.wand_solve import calibrate

        views = None
        if refine_intrinsics and monitor_views:
            from calibkit import plane_views

            views = plane_views.load_for(intr.quality, rig_path or intrinsics, intr.names)
            if views is not None:
                typer.echo(f"intrinsics refined with the intrinsic step's {len(views)} "
                           f"monitor dots in {len(views.view_camera)} views")
        progress = Progress("wand solve, iterations")
        cal = calibrate(obs, intr, spec.spacing_m, initial, refine_intrinsics, holdout, seed,
                        world, progress=lambda text: progress.update(progress.done + 1, text),
                        extra=extra, target_views=views)
        progress.finish(f"{cal.report['solve']['time_s']:.1f} s in the solver")
        cal.rig.save(out)
        if use_sim:
            true_rig.save(truth_rig_path(out))
        if plots:
            from calibkit import wand_report

            wand_report.plot_layout(cal.rig, cal.solved["xyz"],
                                    out.with_name(out.stem + ".layout.png"))
            wand_report.plot_residuals(cal.rig, cal.solved,
                                       out.with_name(out.stem + ".residuals.png"))
        _print(cal.report)
        if json_path is not None:
            write_json(json_path, cal.report)
        typer.echo(f"wrote {out}" + (f" (true rig in {truth_rig_path(out)})" if use_sim
                                     else ""))


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
        ["wand length error, mean (mm)", s["wand_length_error_mean_mm"],
         h["wand_length_error_mean_mm"]],
        ["wand length error, SD (mm)", s["wand_length_error_sd_mm"],
         h["wand_length_error_sd_mm"]],
        ["mean ray distance (mm)", s["mean_ray_distance_mm"], h["mean_ray_distance_mm"]],
        ["frames", s["frames"], h["frames"]],
    ], ["figure", "solved", "held out"])
    typer.echo(f"\nsolve: {s['iterations']} iterations, {s['time_s']:.1f} s, noise "
               f"{s['noise_px']:.3f} px, {s['outliers']} outliers dropped; world frame: "
               f"{report['world_frame']}")
    for w in report["warnings"]:
        typer.echo(f"warning: {w}")
    typer.echo(f"grade: {report['grade']} ({report['grade_reason']})")
