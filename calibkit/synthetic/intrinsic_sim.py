"""`calibkit intrinsic --sim`: cameras of a simulated rig calibrated from simulated monitor
views, and their errors against the truth.

The estimate sees only the captured dots (rendered frames through the real capture, or
each dot's imaged centre with centroid noise); the true cameras go to NAME.truth.toml and
to the figures' `truth` and `error`, which only scorers read.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from calibkit.calibrate.intrinsic import (
    IntrinsicResult,
    PlaneView,
    calibrate,
    camera_figures,
    monitor_plane_view,
)
from calibkit.calibrate.intrinsic_pipeline import capture_views, make_schedule, write_rig
from calibkit.core.camera import Camera, Rig
from calibkit.core.errors import UserError
from calibkit.synthetic.monitor import MonitorSimConfig, make_monitor_sim, projected_dots
from calibkit.synthetic.runs import sim_hardware
from projector.patterns import Schedule


@dataclass(frozen=True, eq=False)
class MonitorSimRun:
    """The hardware, the cameras to calibrate, the monitor and the schedule it shows."""

    hardware: Rig
    names: list[str]
    config: MonitorSimConfig
    schedule: Schedule

    @property
    def pitch_mm(self) -> float:
        return self.config.pixel_pitch_mm


@dataclass(frozen=True, eq=False)
class CameraRun:
    """One camera's calibration: its result, its true camera and the views it used."""

    name: str
    result: IntrinsicResult
    truth: Camera
    views: list[PlaneView]


def setup(sim_rig: Path | None, cameras: int, volume_m: float, size: tuple[int, int] | None,
          seed: int, camera: str, fill: float, noise_px: float, latency_ms: float,
          noise_dn: float, pixel_pitch_mm: float | None, step: float, shifts: int,
          radius: float, raster: bool) -> MonitorSimRun:
    """The hardware (--sim-rig, else a ring from --cameras, --volume, --seed, --size),
    the cameras to calibrate (`camera`, or every one for 'all'), the monitor."""
    if sim_rig is not None and size is not None:
        raise UserError("give --size or --sim-rig, not both: the rig file sets each camera's "
                        "size")
    if not 0.1 <= fill <= 3.0:
        raise UserError(f"--fill must be between 0.1 and 3, got {fill}")
    if noise_px < 0:
        raise UserError(f"--noise-px must not be negative, got {noise_px}")
    hardware = sim_hardware(sim_rig, cameras, volume_m, seed, size or (640, 480))
    if camera not in hardware.names and camera != "all":
        where = f"--sim-rig {sim_rig}" if sim_rig is not None else "the simulated rig"
        raise UserError(f"camera '{camera}' is not in {where} (it has "
                        f"{', '.join(hardware.names)}); or give --camera all")
    names = list(hardware.names) if camera == "all" else [camera]
    cfg = MonitorSimConfig(latency_s=latency_ms / 1000.0, noise_dn=noise_dn)
    cfg.pixel_pitch_mm = pixel_pitch_mm or cfg.pixel_pitch_mm
    schedule = make_schedule(cfg.screen_px, step, shifts, radius, raster)
    return MonitorSimRun(hardware, names, cfg, schedule)


def sim_views(truth: Camera, n_views: int, cfg: MonitorSimConfig, schedule: Schedule,
              fill: float, render: bool, noise_px: float, samples: int, progress,
              say) -> list[PlaneView]:
    """The monitor views a simulated camera (`truth`, the hardware) delivers: rendered and
    captured as a live camera would be, or (no render) the capture's output directly."""
    pitch = cfg.pixel_pitch_mm
    with make_monitor_sim(n_views, truth.size, cfg.seed, cfg, camera=truth,
                          fill=fill) as simulator:
        if render:
            return capture_views(simulator, schedule, n_views, pitch,
                                 lambda v, done: simulator.set_view(v), truth.size, samples,
                                 progress, say)
        rng = np.random.default_rng(cfg.seed + 101)
        return [monitor_plane_view(projected_dots(truth, view, schedule.points_xy,
                                                  schedule.radius_px, pitch, noise_px, rng),
                                   schedule, pitch, f"view{v + 1}")
                for v, view in enumerate(simulator.views)]


def camera_config(run: MonitorSimRun, name: str) -> MonitorSimConfig:
    """The monitor as camera `name` sees it: each camera is held in front of it its own
    way (its own seed)."""
    return dataclasses.replace(run.config, seed=run.config.seed
                               + 1000 * run.hardware.index(name))


def calibrate_cameras(run: MonitorSimRun, n_views: int, fill: float, render: bool,
                      noise_px: float, samples: int, fix_skew: bool, fix_k3: bool,
                      radius: float, rig_path: Path | None, progress, say
                      ) -> Iterator[CameraRun]:
    """Each camera, held in front of the monitor its own way, captured and calibrated;
    written to `rig_path` as soon as it is done (an interruption keeps those done)."""
    for name in run.names:
        truth = run.hardware[name]
        cfg = camera_config(run, name)
        views = sim_views(truth, n_views, cfg, run.schedule, fill, render, noise_px, samples,
                          progress, say)
        result = calibrate(views, truth.size, name, fix_skew=fix_skew, fix_k3=fix_k3,
                           dot_radius_m=radius * run.pitch_mm / 1000.0)
        if rig_path is not None:
            write_rig(rig_path, result.camera, result)
        yield CameraRun(name, result, truth, views)


def truth_error(result: IntrinsicResult, truth: Camera) -> dict:
    """Focal lengths (relative) and principal point (px) against the true camera."""
    return {"fx_rel": (result.camera.fx - truth.fx) / truth.fx,
            "fy_rel": (result.camera.fy - truth.fy) / truth.fy,
            "cx_px": result.camera.cx - truth.cx, "cy_px": result.camera.cy - truth.cy}


def figures(done: list[CameraRun], render: bool, noise_px: float) -> dict:
    """The JSON figures: one camera's, or every camera's with the capture settings."""
    per = []
    for r in done:
        f = r.result.figures()
        f.update(camera=r.name, truth=camera_figures(r.truth),
                 error=truth_error(r.result, r.truth))
        per.append(f)
    if len(done) == 1:
        return per[0]
    return {"cameras": per, "render": render, "noise_px": None if render else noise_px}
