"""`calibkit intrinsic`: a camera's intrinsics from dots on a monitor, a printed board, or --sim."""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path
from typing import Annotated

import numpy as np
import typer

from calibkit import plane_views
from calibkit.camera import Camera, Rig
from calibkit.clitools import Progress, print_table, write_json
from calibkit.errors import UserError
from calibkit.fileio import write_bytes_atomic
from calibkit.intrinsic import (
    PARAMS,
    IntrinsicResult,
    PlaneView,
    calibrate,
    camera_figures,
    distortion_plot_png,
    guidance,
    monitor_plane_view,
)
from projector.patterns import Schedule, coded_schedule, raster_schedule
from projector.screens import parse_pixel_pitch


def _schedule(screen_px: tuple[int, int], step: float, shifts: int, radius: float,
              raster: bool) -> Schedule:
    try:
        if raster:
            return raster_schedule(screen_px, step, radius)
        return coded_schedule(screen_px, step, shifts, radius)
    except ValueError as exc:
        raise UserError(f"dot pattern: {exc}") from None


def _capture(device, schedule: Schedule, n_views: int, pitch_mm: float, next_view, size,
             samples: int) -> list[PlaneView]:
    """Every view: the user (or the simulator) tilts, the schedule runs, guidance follows."""
    from calibkit.dotcapture import DotCapture

    cap = DotCapture(device, schedule, samples=samples)
    views: list[PlaneView] = []
    for v in range(n_views):
        next_view(v, views)
        progress = Progress(f"view {v + 1}/{n_views}", len(schedule.frames))
        dots = cap.run(progress=lambda done, total, p=progress: p.update(done))
        view = monitor_plane_view(dots, schedule, pitch_mm, f"view{v + 1}")
        views.append(view)
        progress.finish(f"{len(view)} dots, {dots.frames} frames "
                        f"({dots.frames / 30.0:.1f} s at 30 fps)")
        if dots.dot_radius_px > 5.0:
            print(f"the dots are {dots.dot_radius_px:.1f} px in radius in the image; their "
                  "perspective bias is corrected, but smaller dots (--radius) are more "
                  "accurate", file=sys.stderr)
        print(guidance(views, size, n_views), file=sys.stderr)
    return views


class _LiveDevice:
    """A monitor window and a live camera as one DotDevice."""

    def __init__(self, window, source) -> None:
        self.window = window
        self.frames = iter(source)

    def show(self, dots) -> None:
        self.window.show(dots)

    def grab(self) -> np.ndarray:
        try:
            return next(self.frames).image
        except StopIteration:
            raise UserError("the camera stopped delivering frames") from None


def _write_rig(path: Path, camera: Camera, result: IntrinsicResult) -> None:
    """Add or update the camera's intrinsics in a rig file, keeping its pose if present."""
    if path.exists():
        rig = Rig.load(path)
        if camera.name in rig.names:
            old = rig[camera.name]
            rig = rig.replace_camera(camera.replace(rvec=old.rvec, t=old.t))
        else:
            rig = dataclasses.replace(rig, cameras=(*rig.cameras, camera))
    else:
        rig = Rig((camera,))
    quality = dict(rig.quality)
    intr = dict(quality.get("intrinsic", {}))
    # std: one standard deviation per parameter (intrinsic.PARAMS), the prior the wand
    # solve gives these intrinsics when it refines them; views_file: the views themselves,
    # which the wand solve takes into its graph instead when it finds them
    intr[camera.name] = {"rms_px": result.rms_px, "views": len(result.rvecs),
                         "points": result.points, "coverage": result.coverage,
                         "std": {k: float(v) for k, v in result.std.items()}}
    if result.views:
        vpath = plane_views.views_path(path)
        plane_views.save(vpath, plane_views.merge(
            plane_views.load_existing(vpath),
            plane_views.from_result(camera.name, result.views, result)))
        intr[camera.name][plane_views.KEY] = vpath.name
    quality["intrinsic"] = intr
    rig = dataclasses.replace(rig, quality=quality)
    rig.save(path)


def _report(result: IntrinsicResult) -> None:
    c = result.camera
    values = [c.fx, c.fy, c.cx, c.cy, c.skew, *c.dist]
    rows = [[name, float(v), float(result.std[name])]
            for name, v in zip(PARAMS, values, strict=True)]
    print_table(rows, ["parameter", "value", "std"])
    per_view = ", ".join(f"{e:.3f}" for e in result.view_rms_px)
    print(f"{c.name}: {result.points} points in {len(result.rvecs)} views, reprojection RMS "
          f"{result.rms_px:.3f} px (per view {per_view}), image coverage "
          f"{100 * result.coverage:.0f}%, inliers {100 * result.inliers.mean():.1f}%")


def _truth_error(result: IntrinsicResult, truth: Camera) -> dict:
    return {"fx_rel": (result.camera.fx - truth.fx) / truth.fx,
            "fy_rel": (result.camera.fy - truth.fy) / truth.fy,
            "cx_px": result.camera.cx - truth.cx, "cy_px": result.camera.cy - truth.cy}


def _sim_views(truth: Camera, n_views: int, cfg, schedule: Schedule, fill: float,
               render: bool, noise_px: float, samples: int) -> list[PlaneView]:
    """The monitor views a simulated camera (`truth`, the hardware) delivers: rendered and
    captured as a live camera would be, or (no render) the capture's output directly."""
    from calibkit.synthetic.monitor import make_monitor_sim, projected_dots

    pitch = cfg.pixel_pitch_mm
    with make_monitor_sim(n_views, truth.size, cfg.seed, cfg, camera=truth,
                          fill=fill) as simulator:
        if render:
            return _capture(simulator, schedule, n_views, pitch,
                            lambda v, done: simulator.set_view(v), truth.size, samples)
        rng = np.random.default_rng(cfg.seed + 101)
        return [monitor_plane_view(projected_dots(truth, view, schedule.points_xy,
                                                  schedule.radius_px, pitch, noise_px, rng),
                                   schedule, pitch, f"view{v + 1}")
                for v, view in enumerate(simulator.views)]


def _sim_summary(rows: list[tuple[str, IntrinsicResult, Camera]]) -> None:
    """One line per camera when a whole rig was calibrated."""
    table = []
    for name, result, truth in rows:
        c, e = result.camera, _truth_error(result, truth)
        table.append([name, result.points, len(result.rvecs), result.rms_px, c.fx,
                      result.std["fx"], c.cx, c.cy, c.dist[0], 100 * e["fx_rel"], e["cx_px"],
                      e["cy_px"]])
    print_table(table, ["camera", "points", "views", "rms_px", "fx", "fx_std", "cx", "cy",
                        "k1", "vs_truth_fx_%", "vs_truth_cx_px", "vs_truth_cy_px"])


def register(app: typer.Typer) -> None:
    @app.command("intrinsic")
    def intrinsic_command(
        display: Annotated[bool, typer.Option(
            "--display", help="Show dots on a monitor and watch them with a live camera.")]
        = False,
        images: Annotated[Path | None, typer.Option(
            help="A folder of images of a printed board (with --board).")] = None,
        board: Annotated[str | None, typer.Option(
            help="chessboard:COLSxROWS:SQUARE_MM, charuco:COLSxROWS:SQUARE_MM:MARKER_MM"
                 "[:DICT] or circles:COLSxROWS:SPACING_MM[:asym].")] = None,
        sim: Annotated[bool, typer.Option(
            "--sim", help="A camera of a simulated rig (--sim-rig) watching a simulated "
                          "monitor; the true rig goes to NAME.truth.toml beside --rig.")] = False,
        views: Annotated[int, typer.Option(help="Views to take (monitor and --sim).")] = 6,
        camera: Annotated[str, typer.Option(
            help="The camera's name in the rig file; --sim: a camera of the simulated rig, "
                 "or 'all' for every one.")] = "cam0",
        device: Annotated[int, typer.Option(help="--display: camera device number.")] = 0,
        monitor: Annotated[int, typer.Option(
            help="--display: monitor index (see `calibkit displays`).")] = 0,
        pixel_pitch_text: Annotated[str | None, typer.Option(
            "--pixel-pitch", help="Monitor pixel pitch: mm per pixel, or WIDTH_MM/WIDTH_PX "
                                  "(overrides the reported one).")]
        = None,
        step: Annotated[float, typer.Option(help="Dot grid step, screen pixels.")] = 80.0,
        shifts: Annotated[int, typer.Option(
            help="The grid is shown SHIFTS x SHIFTS times, offset by step/SHIFTS.")] = 2,
        radius: Annotated[float, typer.Option(help="Dot radius, screen pixels.")] = 6.0,
        raster: Annotated[bool, typer.Option(
            "--raster", help="One dot at a time (the slow original scan).")] = False,
        samples: Annotated[int, typer.Option(help="Frames averaged per pattern.")] = 3,
        fix_k3: Annotated[bool, typer.Option("--fix-k3", help="Keep k3 at 0.")] = False,
        estimate_skew: Annotated[bool, typer.Option(
            "--skew", help="Estimate the skew too (0 otherwise).")] = False,
        rig: Annotated[Path | None, typer.Option(
            help="Write or update the camera in this rig file.")] = None,
        plot: Annotated[Path | None, typer.Option(help="Write the distortion plot (PNG).")]
        = None,
        json_path: Annotated[Path | None, typer.Option(
            "--json", help="Write the figures as JSON.")] = None,
        sim_rig: Annotated[Path | None, typer.Option(
            "--sim-rig", help="--sim: the simulated hardware, a true rig (calibkit sim rig); "
                              "default: a ring made from --cameras, --volume, --seed.")]
        = None,
        cameras: Annotated[int, typer.Option(
            help="--sim without --sim-rig: cameras of the simulated rig.")] = 6,
        volume: Annotated[float, typer.Option(
            help="--sim without --sim-rig: metres across the simulated volume.")] = 4.0,
        render: Annotated[bool, typer.Option(
            "--render/--no-render", help="--sim: render every camera frame and capture it "
                                         "(slow), or report each dot's imaged centre with "
                                         "--noise-px noise (fast, for whole rigs).")] = True,
        noise_px: Annotated[float, typer.Option(
            "--noise-px", help="--sim --no-render: centroid noise of a captured dot per axis, "
                               "px (0.035 leaves the rendered capture's 0.05 px "
                               "residual).")] = 0.035,
        seed: Annotated[int, typer.Option(help="--sim: random seed.")] = 0,
        size: Annotated[str | None, typer.Option(
            help="--sim without --sim-rig: camera size (default 640x480).")] = None,
        latency_ms: Annotated[float, typer.Option(help="--sim: display latency.")] = 70.0,
        noise: Annotated[float, typer.Option(help="--sim: sensor noise, DN.")] = 2.0,
        fill: Annotated[float, typer.Option(
            help="--sim: how much of the image the monitor spans (above 1 it overflows "
                 "the image).")] = 0.8,
    ) -> None:
        """Calibrate one camera's intrinsics (focal lengths, principal point, distortion)."""
        modes = [name for name, on in (("--display", display), ("--images", images is not None),
                                       ("--sim", sim)) if on]
        if len(modes) != 1:
            raise UserError("choose one of --display, --images DIR --board SPEC, or --sim")
        if camera == "all" and not sim:
            raise UserError("--camera all calibrates every camera of a simulated rig: with "
                            "--sim only; name the camera (e.g. --camera cam0)")
        if views < 3 and not images:
            raise UserError(f"--views must be at least 3 (got {views}): one view cannot "
                            "separate the focal length from the distance")
        if samples < 1:
            raise UserError(f"--samples must be >= 1, got {samples}")
        pixel_pitch = parse_pixel_pitch(pixel_pitch_text)
        dot_radius_m = 0.0
        if images is not None:
            if board is None:
                raise UserError("--images needs --board, e.g. --board chessboard:9x6:25")
            from calibkit.board import board_views, parse_board

            spec = parse_board(board)
            progress = Progress("images", None)
            found, img_size, missed = board_views(images, spec,
                                                  lambda d, t: progress.update(d))
            progress.finish()
            if missed:
                print(f"board not found in {len(missed)} image(s): {', '.join(missed)}",
                      file=sys.stderr)
            target_views = found
        elif sim:
            _sim_command(sim_rig, cameras, volume, size, seed, camera, views, fill, render,
                         noise_px, latency_ms, noise, pixel_pitch, step, shifts, radius,
                         raster, samples, estimate_skew, fix_k3, rig, json_path, plot)
            return
        else:
            from calibkit.sources import DeviceSource
            from projector.display import WindowDisplay
            from projector.screens import pick_screen, require_display

            require_display()  # before anything else: the commonest mistake (ssh, CI)
            with DeviceSource(device, camera=camera) as source:
                screen, pitch = pick_screen(monitor, pixel_pitch)
                schedule = _schedule((screen.width_px, screen.height_px), step, shifts,
                                     radius, raster)
                first = next(iter(source), None)
                if first is None:
                    raise UserError(f"camera device {device} gives no frames")
                img_size = (first.image.shape[1], first.image.shape[0])
                window = WindowDisplay(monitor)

                def next_view(v: int, done: list) -> None:
                    input(f"view {v + 1}/{views}: hold the monitor in view, tilted, then "
                          "press Enter ")

                try:
                    target_views = _capture(_LiveDevice(window, source), schedule, views,
                                           pitch, next_view, img_size, samples)
                finally:
                    window.close()
            dot_radius_m = radius * pitch / 1000.0
        result = calibrate(target_views, img_size, camera, fix_skew=not estimate_skew,
                           fix_k3=fix_k3, dot_radius_m=dot_radius_m)
        _report(result)
        figures = result.figures()
        figures["camera"] = camera
        if rig is not None:
            _write_rig(rig, result.camera, result)
            print(f"camera {camera} written to {rig}")
        if plot is not None:
            uv = np.concatenate([v.uv for v in target_views])
            write_bytes_atomic(plot, distortion_plot_png(result, uv))
        if json_path is not None:
            write_json(json_path, figures)


def _sim_command(sim_rig, cameras, volume, size, seed, camera, views, fill, render, noise_px,
                 latency_ms, noise, pixel_pitch, step, shifts, radius, raster, samples,
                 estimate_skew, fix_k3, rig, json_path, plot) -> None:
    """--sim: one camera of the simulated rig (or all of them) calibrated from simulated
    monitor views. The estimate sees only the captured dots; the truth goes to
    NAME.truth.toml beside --rig and to the figures, for scoring."""
    from calibkit.commands.common import parse_size, sim_hardware, truth_rig_path
    from calibkit.synthetic.monitor import MonitorSimConfig

    if sim_rig is not None and size is not None:
        raise UserError("give --size or --sim-rig, not both: the rig file sets each camera's "
                        "size")
    if not 0.1 <= fill <= 3.0:
        raise UserError(f"--fill must be between 0.1 and 3, got {fill}")
    if noise_px < 0:
        raise UserError(f"--noise-px must not be negative, got {noise_px}")
    hardware = sim_hardware(sim_rig, cameras, volume, seed, parse_size(size or "640x480"))
    names = hardware.names if camera == "all" else [camera]
    if camera not in hardware.names and camera != "all":
        where = f"--sim-rig {sim_rig}" if sim_rig is not None else "the simulated rig"
        raise UserError(f"camera '{camera}' is not in {where} (it has "
                        f"{', '.join(hardware.names)}); or give --camera all")
    cfg0 = MonitorSimConfig(latency_s=latency_ms / 1000.0, noise_dn=noise)
    pitch = pixel_pitch or cfg0.pixel_pitch_mm
    cfg0.pixel_pitch_mm = pitch
    schedule = _schedule(cfg0.screen_px, step, shifts, radius, raster)
    if plot is not None and len(names) > 1:
        raise UserError("--plot draws one camera's distortion: give --camera NAME with it")
    done: list[tuple[str, IntrinsicResult, Camera]] = []
    progress = Progress("cameras", len(names), enabled=len(names) > 1)
    for k, name in enumerate(names):
        truth = hardware[name]
        # each camera is held in front of the monitor its own way
        cfg = dataclasses.replace(cfg0, seed=seed + 1000 * hardware.index(name))
        target_views = _sim_views(truth, views, cfg, schedule, fill, render, noise_px,
                                 samples)
        result = calibrate(target_views, truth.size, name, fix_skew=not estimate_skew,
                           fix_k3=fix_k3, dot_radius_m=radius * pitch / 1000.0)
        done.append((name, result, truth))
        if rig is not None:  # after every camera: an interruption keeps those done
            _write_rig(rig, result.camera, result)
        if len(names) == 1:
            _report(result)
            e = _truth_error(result, truth)
            print(f"against the simulator's truth: fx {100 * e['fx_rel']:+.4f}%, fy "
                  f"{100 * e['fy_rel']:+.4f}%, cx {e['cx_px']:+.3f} px, cy "
                  f"{e['cy_px']:+.3f} px")
        progress.update(k + 1, f"{name}: {result.points} dots, rms {result.rms_px:.3f} px")
    progress.finish()
    if len(names) > 1:
        _sim_summary(done)
    if rig is not None:
        hardware.save(truth_rig_path(rig))
        print(f"{'cameras' if len(names) > 1 else 'camera'} {', '.join(names)} written to "
              f"{rig} (true rig in {truth_rig_path(rig)})")
    if plot is not None:
        uv = np.concatenate([v.uv for v in target_views])
        write_bytes_atomic(plot, distortion_plot_png(done[0][1], uv))
    if json_path is not None:
        per = []
        for name, result, truth in done:
            f = result.figures()
            f.update(camera=name, truth=camera_figures(truth), error=_truth_error(result, truth))
            per.append(f)
        write_json(json_path, per[0] if len(names) == 1 else {
            "cameras": per, "render": render,
            "noise_px": None if render else noise_px})
