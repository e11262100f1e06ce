"""The projector extrinsic calibration from end to end, as `calibkit extrinsic --projector`
runs it: plan the sessions, capture them, solve, write the files.

Each step is a function of what the previous one gave, so the command handler only parses
its options and prints, and the simulator (calibkit.synthetic.extrinsic_sim) can stand in
for the capture step without the rest knowing.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import numpy as np

from calibkit.calibrate import plane_views
from calibkit.calibrate.extrinsic_capture import (
    CameraDots,
    ProjectorRig,
    SessionCapture,
    assemble,
    capture_session,
    save_dots,
)
from calibkit.calibrate.extrinsic_reference import (
    PlaneMap,
    References,
    plane_maps,
    reference_layout_px,
    references_toml,
    table_schedule,
)
from calibkit.calibrate.extrinsic_report import floor_recording
from calibkit.calibrate.extrinsic_solve import ExtrinsicResult, SolveOptions, calibrate
from calibkit.core.camera import Rig
from calibkit.core.errors import UserError
from calibkit.core.fileio import write_text_atomic
from calibkit.core.recording import save_observations
from projector.patterns import Schedule, coded_schedule

# a plane map whose reference points disagree by more than this is suspect
MAP_WARN_MM = 15.0
CAMERA_FPS = 30.0  # the capture time is reported at this camera rate


class ProgressSink(Protocol):
    """Where a session's progress goes (calibkit.clitools.Progress fits)."""

    def update(self, done: int, extra: str = "") -> None: ...

    def finish(self, extra: str = "") -> None: ...


ProgressFactory = Callable[[str, int], ProgressSink]


@dataclass(frozen=True, eq=False)
class Sessions:
    """What the projector will show: the plane maps, the floor session's schedule and, with
    the table, the table session's (only the dots that land on the table top)."""

    projector_px: tuple[int, int]
    floor_map: PlaneMap
    table_map: PlaneMap | None
    schedule: Schedule
    table_schedule: Schedule | None

    @property
    def with_table(self) -> bool:
        return self.table_map is not None


@dataclass(frozen=True, eq=False)
class Captured:
    """Both sessions' identified dots per camera, and the camera frames they took
    (estimated: counted from the latencies, not from frames grabbed)."""

    floor: list[CameraDots]
    table: list[CameraDots] | None
    frames: int
    estimated: bool = False


def write_template(path: Path, projector_px: tuple[int, int]) -> int:
    """A reference-points file to fill in with a tape; returns the number of dots in it."""
    layout = reference_layout_px(projector_px)
    refs = References(layout, np.full((len(layout), 2), np.nan), projector_size=projector_px)
    write_text_atomic(path, references_toml(
        refs, "Reference dots: replace each nan with where the dot lands on the\n"
              "floor, x and y in metres from your chosen origin (docs/extrinsic.md)."
              "\nFor the table add [table] height_m and [[table.point]] entries."))
    return len(layout)


def shown_references(refs: References | None, projector_px: tuple[int, int]) -> np.ndarray:
    """The projector pixels of the reference dots to light: the file's, else the template
    layout's."""
    if refs is None:
        return reference_layout_px(projector_px)
    return np.concatenate([refs.floor_px, refs.table_px])


def table_session(refs: References, table: bool | None) -> bool:
    """Whether to run the table session: as asked (table), else (None) when the references
    have a table."""
    if table and not refs.has_table:
        raise UserError("--table needs the table in the reference-points file: add [table] "
                        "with height_m and at least 4 [[table.point]] entries")
    return refs.has_table if table is None else table


def plan_sessions(refs: References, table: bool | None, step_px: float, shifts: int,
                  radius_px: float) -> Sessions:
    """The plane maps and schedules. table: run the table session (None: when the
    references have a table)."""
    with_table = table_session(refs, table)
    floor_map, table_map = plane_maps(refs)
    if not with_table:
        table_map = None
    try:
        schedule = coded_schedule(refs.projector_size, step_px, shifts, radius_px)
    except ValueError as exc:
        raise UserError(f"dot pattern: {exc}") from None
    tsched = table_schedule(schedule, table_map) if table_map is not None else None
    return Sessions(refs.projector_size, floor_map, table_map, schedule, tsched)


def map_notes(sessions: Sessions) -> tuple[list[str], list[str]]:
    """How well each plane map fits its reference points: lines to show, and warnings for a
    reference point far off the others' fit."""
    lines, warnings = [], []
    for what, pm in (("floor", sessions.floor_map), ("table", sessions.table_map)):
        if pm is None:
            continue
        fit = ("exact with 4 points: add more to check it" if pm.n_points == 4 else
               f"residual RMS {pm.residual_rms_mm:.1f} mm, max {pm.residual_max_mm:.1f} mm")
        lines.append(f"{what} map from {pm.n_points} reference points: {fit}")
        if pm.residual_max_mm > MAP_WARN_MM:
            warnings.append(f"a {what} reference point is {pm.residual_max_mm:.0f} mm off the "
                            "others' fit: re-measure it")
    return lines, warnings


def run_session(device: ProjectorRig, schedule: Schedule, n_cameras: int, label: str,
                samples: int, progress: ProgressFactory | None = None,
                latency_frames: list[int | None] | None = None) -> SessionCapture:
    """One session (floor or table) through `device`, its progress shown as it goes."""
    sink = progress(f"{label} dots", len(schedule.frames)) if progress else None
    cap = capture_session(device, schedule, n_cameras, samples=samples,
                          progress=(lambda done, total: sink.update(done)) if sink else None,
                          latency_frames=latency_frames)
    if sink is not None:
        sink.finish(f"{cap.frames} camera frames ({cap.frames / CAMERA_FPS:.1f} s at "
                    f"{CAMERA_FPS:.0f} fps)")
    return cap


def capture_sessions(device: ProjectorRig, sessions: Sessions, n_cameras: int, samples: int,
                     progress: ProgressFactory | None = None,
                     before_table: Callable[[], None] | None = None) -> Captured:
    """The floor session, then (with the table) `before_table()` (the user puts the table
    in place) and the table session, which starts from the floor's camera latencies."""
    floor = run_session(device, sessions.schedule, n_cameras, "floor", samples, progress)
    table = None
    if sessions.table_schedule is not None:
        if before_table is not None:
            before_table()
        table = run_session(device, sessions.table_schedule, n_cameras, "table", samples,
                            progress, floor.latency_frames)
    frames = floor.frames + (table.frames if table is not None else 0)
    return Captured(floor.cameras, None if table is None else table.cameras, frames)


def solve(intrinsics: Rig, camera_names: list[str], captured: Captured, sessions: Sessions,
          opts: SolveOptions) -> ExtrinsicResult:
    """Every camera's pose from the captured dots, with the capture's figures in the
    report."""
    dots = assemble(camera_names, captured.floor, captured.table, sessions.schedule,
                    sessions.floor_map, sessions.table_map)
    result = calibrate(intrinsics, dots, sessions.floor_map, sessions.table_map, opts)
    result.report["capture"] = {"frames": captured.frames,
                                "seconds_at_30fps": captured.frames / CAMERA_FPS,
                                "sessions": 1 + int(sessions.with_table),
                                "simulated_frames": captured.estimated}
    return result


def keep_intrinsic_quality(result: ExtrinsicResult, intrinsics: Rig, intrinsics_path: Path,
                           out: Path) -> None:
    """The intrinsics are passed through unchanged, so their figures (the per-parameter
    std the wand solve's priors read, and where the monitor views are kept, now relative to
    `out`) go on with them into the rig file."""
    per = intrinsics.quality.get("intrinsic", {})
    kept = {n: per[n] for n in result.rig.names if n in per}
    if kept:
        quality = plane_views.rebase({"intrinsic": kept}, intrinsics_path, out)
        result.rig = dataclasses.replace(result.rig,
                                         quality={**result.rig.quality, **quality})


def dots_path(out: Path) -> Path:
    return out.with_name(out.stem + ".dots.npz")


def write_outputs(result: ExtrinsicResult, intrinsics: Rig, intrinsics_path: Path,
                  out: Path) -> None:
    """The rig file (with the intrinsics' figures), the dots for the wand step
    (NAME.dots.npz) and, when enough cameras share floor dots, a floor recording
    (NAME.floor.mcrec) for `calibkit wand --floor`."""
    keep_intrinsic_quality(result, intrinsics, intrinsics_path, out)
    result.rig.save(out)
    save_dots(dots_path(out), result.dots, result.inlier)
    rec = floor_recording(result.rig, result.dots, result.inlier)
    if rec is not None:
        save_observations(out.with_name(out.stem + ".floor.mcrec"), rec)
