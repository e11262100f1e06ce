"""The monitor-dot intrinsic calibration from end to end, as `calibkit intrinsic` runs it:
the schedule, the views (monitor capture or board images), and the rig file.

The capture talks to a `DotDevice` (calibkit.calibrate.dotcapture): a monitor window and a
live camera (`LiveMonitor`, both opened by the command), or the simulator
(calibkit.synthetic.intrinsic_sim). Nothing here prints: messages for the user go to the
`say` callback, progress to the progress factory.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from pathlib import Path

import numpy as np

from calibkit.calibrate import plane_views
from calibkit.calibrate.board import board_views, parse_board
from calibkit.calibrate.dotcapture import DotCapture
from calibkit.calibrate.intrinsic import (
    IntrinsicResult,
    PlaneView,
    guidance,
    monitor_plane_view,
)
from calibkit.core.camera import Camera, Rig
from calibkit.core.errors import UserError
from projector.patterns import Schedule, coded_schedule, raster_schedule

CAMERA_FPS = 30.0  # capture times are reported at this camera rate


def make_schedule(screen_px: tuple[int, int], step: float, shifts: int, radius: float,
                  raster: bool) -> Schedule:
    """The dots to show: coded layers, or one dot at a time (raster)."""
    try:
        if raster:
            return raster_schedule(screen_px, step, radius)
        return coded_schedule(screen_px, step, shifts, radius)
    except ValueError as exc:
        raise UserError(f"dot pattern: {exc}") from None


class LiveMonitor:
    """A monitor window and a live camera as one DotDevice (the caller opens and closes
    both)."""

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


def capture_views(device, schedule: Schedule, n_views: int, pitch_mm: float,
                  next_view: Callable[[int, list[PlaneView]], None], size: tuple[int, int],
                  samples: int, progress, say: Callable[[str], None]) -> list[PlaneView]:
    """Every view: the user (or the simulator) tilts (`next_view`), the schedule runs,
    guidance follows (`say`). progress(label, total) gives an object with update(done) and
    finish(text) (calibkit.clitools.Progress)."""
    cap = DotCapture(device, schedule, samples=samples)
    views: list[PlaneView] = []
    for v in range(n_views):
        next_view(v, views)
        sink = progress(f"view {v + 1}/{n_views}", len(schedule.frames))
        dots = cap.run(progress=lambda done, total, p=sink: p.update(done))
        view = monitor_plane_view(dots, schedule, pitch_mm, f"view{v + 1}")
        views.append(view)
        sink.finish(f"{len(view)} dots, {dots.frames} frames "
                    f"({dots.frames / CAMERA_FPS:.1f} s at {CAMERA_FPS:.0f} fps)")
        if dots.dot_radius_px > 5.0:
            say(f"the dots are {dots.dot_radius_px:.1f} px in radius in the image; their "
                "perspective bias is corrected, but smaller dots (--radius) are more "
                "accurate")
        say(guidance(views, size, n_views))
    return views


def board_capture(images: Path, board: str, progress
                  ) -> tuple[list[PlaneView], tuple[int, int], list[str]]:
    """The views of a printed board in a folder of images (calibkit.calibrate.board)."""
    spec = parse_board(board)
    sink = progress("images", None)
    found, size, missed = board_views(images, spec, lambda d, t: sink.update(d))
    sink.finish()
    return found, size, missed


def write_rig(path: Path, camera: Camera, result: IntrinsicResult) -> None:
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
