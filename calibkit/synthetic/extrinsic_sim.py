"""`calibkit extrinsic --projector --sim`: the simulated projector, table and tape, the
simulated capture, and the score against the truth.

The estimate sees only what hardware would give: the tape-measured reference points (with
their error), the table's tape-measured height (with its own error: a vertical reading at
the corners, TAPE_HEIGHT_ERROR_MM), the identified dots (rendered and captured, or projected
with centroid noise), and the estimated intrinsics. The true rig goes to NAME.truth.toml,
and it and the true table height to the report's `truth` figures, which only scorers read.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from calibkit.calibrate.compare import compare_rigs
from calibkit.calibrate.extrinsic_capture import capture_frames_estimate
from calibkit.calibrate.extrinsic_pipeline import (
    Captured,
    ProgressFactory,
    Sessions,
    capture_sessions,
)
from calibkit.calibrate.extrinsic_reference import (
    References,
    reference_layout_px,
    references_toml,
)
from calibkit.calibrate.extrinsic_solve import ExtrinsicResult
from calibkit.core.camera import Rig
from calibkit.core.errors import UserError
from calibkit.core.fileio import write_text_atomic
from calibkit.synthetic import projector as sp
from calibkit.synthetic.runs import (
    check_estimate,
    need_intrinsics_for_sim,
    sim_hardware,
    truth_rig_path,
)

# SD of the tape's table height: docs/extrinsic.md has the user measure it at two or three
# corners that "should agree within 2 mm", and the solve's --height-sigma-mm says 2 mm.
TAPE_HEIGHT_ERROR_MM = 2.0


@dataclass(frozen=True, eq=False)
class ProjectorSimRun:
    """A simulated run: the scene (true rig, projector, table), what the tape measured,
    and the seed the capture draws its noise from."""

    scene: sp.ProjectorScene
    refs: References
    intrinsics: Rig  # the estimate file's, which the calibration starts from
    seed: int

    @property
    def truth(self) -> Rig:
        return self.scene.rig


def setup(intrinsics_path: Path | None, sim_rig: Path | None, cameras: int | None,
          size: tuple[int, int] | None, volume_m: float, table_height_m: float,
          ref_error_mm: float, projector_px: tuple[int, int], seed: int,
          height_error_mm: float = TAPE_HEIGHT_ERROR_MM) -> ProjectorSimRun:
    """The hardware (the --sim-rig file, else a ring from --cameras, --volume, --seed and
    --size, default 640x480), a ceiling projector and a table over it, and the tape
    measurements of the reference dots (error ref_error_mm per axis) and of the table's
    height (error height_error_mm; both drawn from the seed). The estimate file
    (--intrinsics) must hold the hardware's cameras."""
    if not 0 <= table_height_m < 2.0:
        raise UserError(f"--table-height must be in [0, 2) m, got {table_height_m}")
    if not (ref_error_mm >= 0 and height_error_mm >= 0):
        raise UserError("--ref-error-mm and the height error must be 0 or more (mm)")
    if intrinsics_path is None:
        raise need_intrinsics_for_sim("calibkit extrinsic --projector")
    if sim_rig is not None and (size is not None or cameras is not None):
        raise UserError("give --sim-rig or --cameras/--size, not both: the rig file "
                        "sets the cameras")
    intrinsics = Rig.load(intrinsics_path)
    hardware = sim_hardware(sim_rig, cameras or len(intrinsics), volume_m, seed,
                            size or (640, 480))
    check_estimate(intrinsics, hardware, intrinsics_path, "--intrinsics")
    volume_m = float(hardware.meta.get("volume_m", volume_m))
    scene = sp.scene_for_rig(hardware, volume_m, table_height_m or None, seed)
    tpx = sp.table_reference_px(scene) if scene.table is not None else np.zeros((0, 2))
    m = sp.measured_references(scene, reference_layout_px(projector_px), tpx,
                               ref_error_mm / 1000.0, height_error_mm / 1000.0, seed=seed)
    refs = References(m["floor_px"], m["floor_xy_m"], m.get("table_px", np.zeros((0, 2))),
                      m.get("table_xy_m", np.zeros((0, 2))), m.get("table_height_m"),
                      projector_size=projector_px)
    return ProjectorSimRun(scene, refs, intrinsics, seed)


def capture(run: ProjectorSimRun, sessions: Sessions, samples: int, render: bool,
            noise_px: float, progress: ProgressFactory | None = None) -> Captured:
    """The sessions as the simulated cameras see them: rendered frames through the real
    capture (render), or each dot's true image position with noise_px centroid noise and
    the camera frames estimated from the simulated latencies."""
    cfg = sp.ProjectorSimConfig(projector_px=sessions.projector_px, seed=run.seed)
    n = len(run.scene.rig)
    if render:
        with sp.ProjectorRigSim(run.scene, cfg) as dev:
            return capture_sessions(dev, sessions, n, samples, progress,
                                    before_table=lambda: dev.set_table(True))
    schedule, tsched = sessions.schedule, sessions.table_schedule
    floor = sp.simulated_dots(run.scene, schedule.points_xy, False, noise_px, seed=run.seed)
    lat = sp.latency_frames(cfg, n)
    frames = capture_frames_estimate(schedule, lat, samples)
    table = None
    if tsched is not None:
        table = sp.simulated_dots(run.scene, schedule.points_xy, True, noise_px,
                                  seed=run.seed + 1, shown=np.concatenate(tsched.layers))
        frames += capture_frames_estimate(tsched, lat, samples)
    return Captured(floor, table, frames, estimated=True)


def score(run: ProjectorSimRun, result: ExtrinsicResult, out: Path) -> dict:
    """The calibrated rig against the truth (in the tape's frame, not aligned), put in the
    report as `truth`; the true rig and the simulated tape file written beside `out`."""
    run.truth.save(truth_rig_path(out))
    write_text_atomic(out.with_name(out.stem + ".refs.toml"), references_toml(
        run.refs, "simulated tape measurements (calibkit extrinsic --sim)"))
    cmp = compare_rigs(run.truth, result.rig, align=False)
    truth = {"cameras": cmp["cameras"],
             "position_error_max_mm": max(c["position_mm"] for c in cmp["cameras"]),
             "rotation_error_max_deg": max(c["rotation_deg"] for c in cmp["cameras"]),
             "scale_error_ppm": cmp["scale"]["error_ppm"]}
    if run.scene.table is not None:
        true_m = run.scene.table.height_m
        h = result.report.get("table_height") or {}
        tape = run.refs.table_height_m
        truth["table_height"] = {
            "true_m": true_m, "tape_error_mm": 1000.0 * (tape - true_m),
            "used_error_mm": 1000.0 * (h.get("used_m", tape) - true_m),
            "best_error_mm": 1000.0 * (h.get("best_m", tape) - true_m)}
    result.report["truth"] = truth
    return truth
