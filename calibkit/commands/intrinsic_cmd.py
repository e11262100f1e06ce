"""`calibkit intrinsic`: a camera's intrinsics from dots on a monitor, a printed board, or --sim."""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path
from typing import Annotated

import numpy as np
import typer

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
    intr[camera.name] = {"rms_px": result.rms_px, "views": len(result.rvecs),
                         "points": result.points, "coverage": result.coverage}
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
            "--sim", help="A simulated camera watching a simulated monitor.")] = False,
        views: Annotated[int, typer.Option(help="Views to take (monitor and --sim).")] = 6,
        camera: Annotated[str, typer.Option(help="The camera's name in the rig file.")]
        = "cam0",
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
        seed: Annotated[int, typer.Option(help="--sim: random seed.")] = 0,
        size: Annotated[str, typer.Option(help="--sim: camera size.")] = "640x480",
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
        if views < 3 and not images:
            raise UserError(f"--views must be at least 3 (got {views}): one view cannot "
                            "separate the focal length from the distance")
        if samples < 1:
            raise UserError(f"--samples must be >= 1, got {samples}")
        pixel_pitch = parse_pixel_pitch(pixel_pitch_text)
        truth: Camera | None = None
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
            plane_views = found
        elif sim:
            from calibkit.commands.common import parse_size
            from calibkit.synthetic.monitor import MonitorSimConfig, make_monitor_sim

            img_size = parse_size(size)
            cfg = MonitorSimConfig(latency_s=latency_ms / 1000.0, noise_dn=noise, seed=seed)
            pitch = pixel_pitch or cfg.pixel_pitch_mm
            cfg.pixel_pitch_mm = pitch
            schedule = _schedule(cfg.screen_px, step, shifts, radius, raster)
            if not 0.1 <= fill <= 3.0:
                raise UserError(f"--fill must be between 0.1 and 3, got {fill}")
            with make_monitor_sim(views, img_size, seed, cfg, fill=fill) as simulator:
                truth = simulator.camera.replace(name=camera)
                plane_views = _capture(simulator, schedule, views, pitch,
                                       lambda v, done: simulator.set_view(v), img_size,
                                       samples)
            dot_radius_m = radius * pitch / 1000.0
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
                    plane_views = _capture(_LiveDevice(window, source), schedule, views,
                                           pitch, next_view, img_size, samples)
                finally:
                    window.close()
            dot_radius_m = radius * pitch / 1000.0
        result = calibrate(plane_views, img_size, camera, fix_skew=not estimate_skew,
                           fix_k3=fix_k3, dot_radius_m=dot_radius_m)
        _report(result)
        figures = result.figures()
        figures["camera"] = camera
        if truth is not None:
            t = camera_figures(truth)
            figures["truth"] = t
            figures["error"] = {
                "fx_rel": (result.camera.fx - truth.fx) / truth.fx,
                "fy_rel": (result.camera.fy - truth.fy) / truth.fy,
                "cx_px": result.camera.cx - truth.cx, "cy_px": result.camera.cy - truth.cy}
            e = figures["error"]
            print(f"against the simulator's truth: fx {100 * e['fx_rel']:+.4f}%, fy "
                  f"{100 * e['fy_rel']:+.4f}%, cx {e['cx_px']:+.3f} px, cy "
                  f"{e['cy_px']:+.3f} px")
        if rig is not None:
            _write_rig(rig, result.camera, result)
            print(f"camera {camera} written to {rig}")
        if plot is not None:
            uv = np.concatenate([v.uv for v in plane_views])
            write_bytes_atomic(plot, distortion_plot_png(result, uv))
        if json_path is not None:
            write_json(json_path, figures)
