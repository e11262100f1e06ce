"""Triangulating a whole recording, as `calibkit triangulate` does: gates that follow the rig's
residual, every frame's blobs matched and triangulated, the figures, the points CSV."""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from calibkit.core.camera import Rig
from calibkit.core.fileio import atomic_write
from calibkit.core.observations import Observations
from calibkit.vision.correspondence import CorrespondenceConfig, FramePoints, match_frames
from calibkit.vision.gates import gated_config

COLUMNS = ("frame", "x", "y", "z", "reproj_px", "ray_mm", "n_cameras", "cameras")


def write_points_csv(path: Path, points: FramePoints, camera_names: list[str],
                     error_mm: np.ndarray | None = None) -> None:
    """The points as CSV (COLUMNS, then error_mm with truth); `cameras` lists the cameras
    that saw each point, separated by ';'."""
    names = np.asarray(camera_names, dtype=object)
    seen = points.rows >= 0
    with atomic_write(path, "w", encoding="utf-8") as handle:
        handle.write(",".join(COLUMNS + (("error_mm",) if error_mm is not None else ())) + "\n")
        for i in range(len(points.frame)):  # file output, not a hot path
            x, y, z = points.xyz[i]
            row = (f"{points.frame[i]},{x:.6f},{y:.6f},{z:.6f},{points.reproj_px[i]:.4f},"
                   f"{points.ray_dist_m[i] * 1000:.4f},{points.n_cameras[i]},"
                   f"{';'.join(names[seen[i]])}")
            if error_mm is not None:
                row += f",{error_mm[i]:.4f}"
            handle.write(row + "\n")



@dataclass
class Reconstruction:
    """What triangulating a recording gave: the points, the gates used and the residual
    they followed (None: the defaults), the figures."""

    points: FramePoints
    config: CorrespondenceConfig
    residual: object | None
    figures: dict


def reconstruct(rig: Rig, obs: Observations, base: CorrespondenceConfig,
                residual_px: float | None, estimate_residual: bool, fixed: set[str],
                progress=None, say=None) -> Reconstruction:
    """Gates from the rig's residual (the rig file's, the one given, or one measured on the
    data's confident matches), then every frame matched and triangulated. `say(line)` is
    told which gates, before the long part starts."""
    started = time.perf_counter()
    cfg, residual = gated_config(rig, obs, residual_px, estimate_residual, base, fixed)
    residual_s = time.perf_counter() - started
    if say is not None:
        say(gates_line(cfg, residual, fixed))
    start = time.perf_counter()
    n_frames = len(obs.frames())
    points = match_frames(rig, obs, cfg, progress=progress)
    elapsed = time.perf_counter() - start
    figures: dict = {
        "frames": n_frames, "points": int(len(points.frame)),
        "points_per_frame": len(points.frame) / n_frames,
        "residual": residual.as_dict() if residual is not None else None,
        "gates": {"epipolar_px": cfg.epipolar_px, "max_reproj_px": cfg.max_reproj_px,
                  "fixed": sorted(fixed)},
        "reproj_px_median": _stat(np.median, points.reproj_px),
        "reproj_px_p95": _stat(lambda a: np.percentile(a, 95), points.reproj_px),
        "ray_mm_median": _stat(np.median, points.ray_dist_m * 1000),
        "n_cameras": {str(k): int(v) for k, v in zip(
            *np.unique(points.n_cameras, return_counts=True), strict=True)},
        "residual_seconds": residual_s,
        "seconds": elapsed, "frames_per_s": n_frames / elapsed if elapsed > 0 else None,
    }
    return Reconstruction(points, cfg, residual, figures)


def gates_line(cfg: CorrespondenceConfig, residual, fixed) -> str:
    """One line saying which residual the gates follow and where it came from."""
    gates = f"epipolar {cfg.epipolar_px:.2f} px, reprojection {cfg.max_reproj_px:.2f} px"
    if {"epipolar_px", "max_reproj_px"} <= set(fixed):
        return f"gates: {gates} (fixed)"
    if residual is None:
        return (f"gates: {gates} (the defaults: the rig file records no residual and the "
                "data gave too few confident matches to measure one)")
    return f"gates: {gates}, following the residual {residual}"


def _stat(fn, values: np.ndarray) -> float:
    v = values[np.isfinite(values)]
    return float(fn(v)) if len(v) else float("nan")
