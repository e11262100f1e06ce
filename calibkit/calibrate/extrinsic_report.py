"""Figures of a projector extrinsic calibration, and what it hands to the wand step.

Per camera: reprojection RMS, dot counts, and the mean ray distance (how far its rays pass
from the dots every calibrated camera triangulates), over all its dots and over the table
dots alone, where a tilt error shows; the plane maps' fit residuals. And a sparse
recording of floor dots seen by three or more cameras, from which `calibkit wand --floor
FILE --floor-kind plane` fits the floor.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from calibkit.calibrate.extrinsic_capture import DotObservations
from calibkit.calibrate.extrinsic_reference import FLOOR, TABLE, PlaneMap
from calibkit.core.camera import Rig
from calibkit.core.geometry import RigArrays, mean_ray_distance, triangulate
from calibkit.core.observations import Observations

if TYPE_CHECKING:
    from calibkit.calibrate.extrinsic_solve import PoseResult


def figures(rig: Rig, poses: list[PoseResult], dots: DotObservations, inlier: np.ndarray,
            floor: PlaneMap, table: PlaneMap | None, xyz: np.ndarray | None = None) -> dict:
    """The report: per camera reprojection RMS (against the dots' positions `xyz`, the
    jointly refined ones when there are, else the plane maps' points), dot counts,
    and the mean ray distance over its dots and over its table dots alone (distance from
    its ray to the dot triangulated by every calibrated camera); overall figures too."""
    sel = dots.select(inlier)
    index = np.array([rig.names.index(n) if n in rig.names else -1 for n in dots.camera_names])
    rows = index[sel.camera] >= 0
    cam, pt, uv = index[sel.camera[rows]], sel.point[rows], sel.uv[rows]
    used, local = np.unique(pt, return_inverse=True)
    tri = triangulate(rig, local, cam, uv, n_points=len(used))
    o, d = RigArrays.from_rig(rig).rays(cam, uv)
    x = tri.xyz[local]
    w = x - o
    ray_to_point = np.linalg.norm(w - np.sum(w * d, axis=1, keepdims=True) * d, axis=1) * 1e3
    on_table = dots.plane[used[local]] == TABLE
    pts_xyz = dots.xyz if xyz is None else np.where(np.isfinite(xyz), xyz, dots.xyz)
    proj, _ = RigArrays.from_rig(rig).project(cam, pts_xyz[pt])
    err = np.sum((proj - uv) ** 2, axis=1)
    per_point = mean_ray_distance(local, o, d, len(used)) * 1000.0
    table_pts = dots.plane[used] == TABLE
    cams = []
    for r in poses:
        k = rig.names.index(r.name) if r.camera is not None else -1
        m = cam == k
        fin = m & np.isfinite(ray_to_point)
        cams.append({
            "name": r.name, "calibrated": r.camera is not None,
            "dots": r.floor_dots + r.table_dots, "floor_dots": r.floor_dots,
            "table_dots": r.table_dots,
            "reprojection_rms_px": float(np.sqrt(np.mean(err[m]))) if m.any() else math.nan,
            "mean_ray_distance_mm": float(np.mean(ray_to_point[fin])) if fin.any()
            else math.nan,
            "mean_ray_distance_table_mm": float(np.mean(ray_to_point[fin & on_table]))
            if (fin & on_table).any() else math.nan,
            "warning": r.warning})

    def nanmean(a):
        a = a[np.isfinite(a)]
        return float(np.mean(a)) if len(a) else math.nan

    return {
        "cameras": cams,
        "calibrated": [r.name for r in poses if r.camera is not None],
        "not_calibrated": [r.name for r in poses if r.camera is None],
        "reprojection_rms_px": float(np.sqrt(np.mean(err))) if len(err) else math.nan,
        "mean_ray_distance_mm": nanmean(per_point),
        "mean_ray_distance_table_mm": nanmean(per_point[table_pts]),
        "mean_ray_distance_floor_mm": nanmean(per_point[~table_pts]),
        "floor_map": {"residual_rms_mm": floor.residual_rms_mm,
                      "residual_max_mm": floor.residual_max_mm, "points": floor.n_points},
        "table_map": None if table is None else {
            "residual_rms_mm": table.residual_rms_mm, "residual_max_mm": table.residual_max_mm,
            "points": table.n_points, "height_m": table.height_m},
        "dots": int(len(used)), "table_dot_points": int(table_pts.sum()),
    }


def floor_recording(rig: Rig, dots: DotObservations, inlier: np.ndarray, n_dots: int = 30,
                    repeats: int = 3):
    """A few well-spread floor dots seen by >= 3 cameras as a recording of static markers:
    `calibkit wand --floor FILE --floor-kind plane` fits the floor plane to them. Sparse, so
    that matching unlabelled blobs across cameras is unambiguous."""
    sel = dots.select(inlier)
    floor_rows = dots.plane[sel.point] == FLOOR
    pts, counts = np.unique(sel.point[floor_rows], return_counts=True)
    cand = pts[counts >= 3]
    if len(cand) == 0:
        return None
    xy = dots.xyz[cand, :2]
    chosen = [int(np.argmin(np.linalg.norm(xy - xy.mean(axis=0), axis=1)))]
    dmin = np.linalg.norm(xy - xy[chosen[0]], axis=1)
    while len(chosen) < min(n_dots, len(cand)):
        k = int(np.argmax(dmin))
        chosen.append(k)
        dmin = np.minimum(dmin, np.linalg.norm(xy - xy[k], axis=1))
    keep = np.isin(sel.point, cand[chosen])
    sub = sel.select(keep)
    marker = np.searchsorted(cand[chosen][np.argsort(cand[chosen])], sub.point)
    n = len(sub)
    frame = np.repeat(np.arange(repeats), n)
    sizes = [rig[n].size if n in rig.names else (0, 0) for n in dots.camera_names]
    return Observations(dots.camera_names, sizes, frame, np.tile(sub.camera, repeats),
                        frame * 33_333_333, np.tile(sub.uv, (repeats, 1)),
                        np.full(n * repeats, 20.0), np.full(n * repeats, 200.0),
                        np.tile(marker, repeats), 30.0).sorted()
