"""How far apart two calibrations of the same rig are: per camera, and in triangulated space.

A calibration without a surveyed world frame is only defined up to a similarity transform
(a wand fixes the scale, not where the origin sits), so by default the second rig is first
aligned to the first by the similarity that best maps its camera centres; that transform
is reported, and the differences are what remains. The grid figure is the one users feel:
a grid of points filling the volume is projected with rig A and triangulated with rig B,
and the RMS of the 3D differences is what B's errors cost in millimetres.
"""

from __future__ import annotations

import math

import numpy as np

from calibkit.core.camera import Camera, Rig, rvec_from_rotation
from calibkit.core.errors import UserError
from calibkit.core.geometry import rigid_fit, triangulate

GRID_STEPS = 12  # points per axis before keeping those that two cameras see


def _angle_deg(R: np.ndarray) -> float:
    return math.degrees(float(np.linalg.norm(rvec_from_rotation(R))))


def similarity_from_rigs(a: list[Camera], b: list[Camera]) -> tuple[np.ndarray, np.ndarray, float]:
    """(R, t, s) with s R c_b + t ~ c_a for the cameras' centres.

    Three or more cameras not on a line fix it from the centres alone (Umeyama); with fewer,
    the rotation comes from the cameras' orientations (the mean of R_a^T R_b, made a
    rotation) and the scale from the distance between the centres.
    """
    ca = np.array([c.centre for c in a])
    cb = np.array([c.centre for c in b])
    spread = np.linalg.svd(cb - cb.mean(axis=0), compute_uv=False) if len(cb) >= 3 else None
    if spread is not None and spread[1] > 1e-6 * max(spread[0], 1e-12):
        return rigid_fit(cb, ca, scale=True)
    M = sum(ca_.R.T @ cb_.R for ca_, cb_ in zip(a, b, strict=True))
    U, _, Vt = np.linalg.svd(M)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    R = U @ D @ Vt
    da = np.linalg.norm(ca - ca.mean(axis=0), axis=1).sum()
    db = np.linalg.norm(cb - cb.mean(axis=0), axis=1).sum()
    s = float(da / db) if db > 1e-12 else 1.0
    return R, ca.mean(axis=0) - s * R @ cb.mean(axis=0), s


def transform_camera(cam: Camera, R: np.ndarray, t: np.ndarray, s: float) -> Camera:
    """The camera expressed in the world X' = s R X + t (its image does not change)."""
    R_new = cam.R @ R.T
    centre = s * R @ cam.centre + t
    return cam.replace(R=R_new, t=-R_new @ centre)


def grid_points(rig: Rig, steps: int = GRID_STEPS) -> np.ndarray:
    """Points filling the rig's capture volume that at least two of its cameras see.

    The volume is the simulator's box when the rig says how large it is, else the box under
    the cameras (their footprint shrunk towards the middle, from the floor to their mean
    height).
    """
    volume = rig.meta.get("volume_m")
    if isinstance(volume, (int, float)) and volume > 0:
        half = volume / 2.0
        lo, hi = np.array([-half, -half, 0.0]), np.array([half, half, half])
    else:
        c = rig.centres()
        mid = c.mean(axis=0)
        lo = mid + 0.6 * (c.min(axis=0) - mid)
        hi = mid + 0.6 * (c.max(axis=0) - mid)
        lo[2], hi[2] = min(0.0, c[:, 2].min()), max(c[:, 2].mean(), 1e-3)
    axes = [np.linspace(lo[k], hi[k], steps) for k in range(3)]
    pts = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    seen = np.zeros(len(pts), dtype=int)
    for cam in rig:
        uv, front = cam.project(pts)
        seen += front & cam.in_image(uv)
    return pts[seen >= 2]


GROSS_MM = 10.0  # a grid point further than this from the truth is a gross error


def grid_rms_mm(a: Rig, b: Rig) -> tuple[float, int, int]:
    """RMS 3D distance (mm) between grid points and their triangulation with rig b from
    rig a's exact projections, the number of grid points used, and how many of them are
    gross errors (over GROSS_MM, or not triangulated at all)."""
    pts = grid_points(a)
    point, camera, uv = [], [], []
    b_index = {name: i for i, name in enumerate(b.names)}
    for cam in a:
        if cam.name not in b_index:
            continue
        px, front = cam.project(pts)
        vis = np.flatnonzero(front & cam.in_image(px))
        point.append(vis)
        camera.append(np.full(len(vis), b_index[cam.name]))
        uv.append(px[vis])
    if not point:
        return float("nan"), 0, 0
    point, camera, uv = np.concatenate(point), np.concatenate(camera), np.concatenate(uv)
    tri = triangulate(b, point, camera, uv, n_points=len(pts), ray_distance=False)
    d = np.linalg.norm(tri.xyz - pts, axis=1)
    lost = int(np.count_nonzero(~np.isfinite(d)))
    d = d[np.isfinite(d)]
    if not len(d):
        return float("nan"), 0, lost
    gross = lost + int(np.count_nonzero(d * 1000.0 > GROSS_MM))
    return float(np.sqrt(np.mean(d**2)) * 1000.0), int(len(d)), gross


def compare_rigs(a: Rig, b: Rig, align: bool = True) -> dict:
    """Per-camera differences of rig b from rig a (cameras matched by name), the grid RMS,
    and the alignment applied to b. Raises UserError when the rigs share no camera."""
    common = [name for name in a.names if name in set(b.names)]
    if not common:
        raise UserError(f"the two rigs have no camera name in common ({', '.join(a.names)} vs "
                        f"{', '.join(b.names)})")
    cams_a = [a[name] for name in common]
    cams_b = [b[name] for name in common]
    if align:
        R, t, s = similarity_from_rigs(cams_a, cams_b)
    else:
        R, t, s = np.eye(3), np.zeros(3), 1.0
    aligned = [transform_camera(c, R, t, s) for c in cams_b]
    rows = []
    for ca, cb in zip(cams_a, aligned, strict=True):
        f_a, f_b = 0.5 * (ca.fx + ca.fy), 0.5 * (cb.fx + cb.fy)
        rows.append({
            "name": ca.name,
            "position_mm": float(np.linalg.norm(ca.centre - cb.centre) * 1000.0),
            "rotation_deg": _angle_deg(ca.R @ cb.R.T),
            "focal_pct": float(100.0 * (f_b - f_a) / f_a),
            "principal_px": float(math.hypot(cb.cx - ca.cx, cb.cy - ca.cy)),
        })
    rig_b = Rig(tuple(aligned))
    rig_a = Rig(tuple(cams_a), meta=dict(a.meta))
    rms, n, gross = grid_rms_mm(rig_a, rig_b)
    return {
        "cameras": rows,
        "grid_rms_mm": rms,
        "grid_points": n,
        "grid_gross_points": gross,
        "alignment": {"applied": bool(align), "rotation_deg": _angle_deg(R),
                      "rotation_vector": rvec_from_rotation(R).tolist(),
                      "translation_m": np.asarray(t, dtype=float).tolist(), "scale": float(s)},
        "only_in_a": [n_ for n_ in a.names if n_ not in set(common)],
        "only_in_b": [n_ for n_ in b.names if n_ not in set(common)],
    }
