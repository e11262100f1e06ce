"""How far apart two calibrations of the same rig are: per camera, and in triangulated space.

A calibration without a surveyed world frame is only defined up to a similarity transform
(a wand fixes the scale, not where the origin sits), so by default the second rig is first
aligned to the first by the similarity that best maps its camera centres; that transform
is reported, and the differences are what remains. The grid figure is the one users feel:
a grid of points filling the volume is projected with rig A and triangulated with rig B,
and the RMS of the 3D differences is what B's errors cost in millimetres.

A similarity absorbs a scale error: a rig 0.3 % too large aligns onto the truth with a grid
RMS of a few hundredths of a millimetre, yet measures 12 mm too much over 4 m. So the scale
is always fitted and judged on its own (what it alone moves the grid points by, in the
grid's own millimetres), and the verdict counts the worse of the two; `scale=False` aligns
with rotation and translation only, leaving the scale error in the grid RMS.
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


def similarity_from_rigs(a: list[Camera], b: list[Camera], scale: bool = True
                         ) -> tuple[np.ndarray, np.ndarray, float]:
    """(R, t, s) with s R c_b + t ~ c_a for the cameras' centres (s = 1 without `scale`:
    a rigid transform, so that a scale error stays in what is compared).

    Three or more cameras not on a line fix it from the centres alone (Umeyama); with fewer,
    the rotation comes from the cameras' orientations (the mean of R_a^T R_b, made a
    rotation) and the scale from the distance between the centres.
    """
    ca = np.array([c.centre for c in a])
    cb = np.array([c.centre for c in b])
    spread = np.linalg.svd(cb - cb.mean(axis=0), compute_uv=False) if len(cb) >= 3 else None
    if spread is not None and spread[1] > 1e-6 * max(spread[0], 1e-12):
        return rigid_fit(cb, ca, scale=scale)
    M = sum(ca_.R.T @ cb_.R for ca_, cb_ in zip(a, b, strict=True))
    U, _, Vt = np.linalg.svd(M)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    R = U @ D @ Vt
    da = np.linalg.norm(ca - ca.mean(axis=0), axis=1).sum()
    db = np.linalg.norm(cb - cb.mean(axis=0), axis=1).sum()
    s = float(da / db) if db > 1e-12 and scale else 1.0
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
    return seen_by_two(rig, lo, hi, steps)


def seen_by_two(rig: Rig, lo: np.ndarray, hi: np.ndarray, steps: int) -> np.ndarray:
    """The points of a steps^3 grid over the box lo..hi that two or more cameras of `rig`
    see: the space a calibration can vouch for (compare's grid, the wand's shape figure)."""
    axes = [np.linspace(lo[k], hi[k], steps) for k in range(3)]
    pts = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    seen = np.zeros(len(pts), dtype=int)
    for cam in rig:
        uv, front = cam.project(pts)
        seen += front & cam.in_image(uv)
    return pts[seen >= 2]


GROSS_MM = 10.0  # a grid point further than this from the truth is a gross error


def grid_rms_mm(a: Rig, b: Rig, pts: np.ndarray | None = None) -> tuple[float, int, int]:
    """RMS 3D distance (mm) between grid points (default: grid_points(a)) and their
    triangulation with rig b from rig a's exact projections, the number of grid points
    used, and how many of them are gross errors (over GROSS_MM, or not triangulated)."""
    pts = grid_points(a) if pts is None else pts
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


# The verdict's levels, each the largest grid RMS (mm) it allows: 0.3 mm is the chain's
# target against the truth, 1 mm the target with 0.5 % / 2 px intrinsic error going in
# (docs/simulator.md), GROSS_MM the line past which a point counts as a gross error.
GRADES = (("excellent", 0.3), ("good", 1.0), ("usable", GROSS_MM))


def scale_figures(s: float | None, grid: np.ndarray) -> dict:
    """What the alignment's scale s (B mapped onto A: s R x_b + t) says about B's lengths.

    error_ppm: how much longer B measures a length than A does (1/s - 1). length_error_mm:
    that error over the grid's diagonal (span_m), the longest length measured in the volume.
    grid_rms_mm: how far the scale alone moves the grid points, RMS about their middle (the
    least any alignment leaves): the currency of the grid RMS, so the verdict can weigh it.
    None values when one camera cannot show a scale."""
    span = float(np.linalg.norm(np.ptp(grid, axis=0))) if len(grid) else 0.0
    rms_radius = float(np.sqrt(np.mean(np.sum((grid - grid.mean(axis=0)) ** 2, axis=1)))) \
        if len(grid) else 0.0
    if s is None or not math.isfinite(s) or s <= 0:
        return {"factor": None, "error_ppm": None, "length_error_mm": None, "span_m": span,
                "grid_rms_mm": None}
    err = 1.0 / s - 1.0
    return {"factor": float(s), "error_ppm": float(err * 1e6),
            "length_error_mm": float(abs(err) * span * 1000.0), "span_m": span,
            "grid_rms_mm": float(abs(err) * rms_radius * 1000.0)}


def verdict(grid_rms_mm: float, gross: int, scale_rms_mm: float | None) -> dict:
    """One grade for B against A: the level the worse of the grid RMS and the scale's own
    grid RMS reaches (a grid point off by more than GROSS_MM caps it at "usable"), and the
    reason in a sentence."""
    worst = max(grid_rms_mm, scale_rms_mm or 0.0) if math.isfinite(grid_rms_mm) else math.inf
    grade = next((name for name, limit in GRADES if worst <= limit), "poor")
    order = [name for name, _ in GRADES] + ["poor"]
    if gross and order.index(grade) < order.index("usable"):
        grade = "usable"
    if not math.isfinite(grid_rms_mm):
        reason = "no grid point was seen by two cameras of both rigs"
    elif gross:
        reason = f"{gross} grid points are off by more than {GROSS_MM:g} mm"
    elif scale_rms_mm is not None and scale_rms_mm > grid_rms_mm:
        reason = (f"the scale alone moves the grid points by {scale_rms_mm:.3f} mm RMS, more "
                  f"than the grid RMS of {grid_rms_mm:.3f} mm")
    else:
        reason = f"grid RMS {grid_rms_mm:.3f} mm"
    limits = ", ".join(f"{name} <= {limit:g} mm" for name, limit in GRADES)
    return {"grade": grade, "reason": reason, "limits": limits}


def compare_rigs(a: Rig, b: Rig, align: bool = True, scale: bool = True) -> dict:
    """Per-camera differences of rig b from rig a (cameras matched by name), the grid RMS,
    the alignment applied to b (a similarity, or with scale=False a rigid transform), the
    scale B's lengths are off by (fitted whether or not it is applied), and a verdict.
    Raises UserError when the rigs share no camera."""
    common = [name for name in a.names if name in set(b.names)]
    if not common:
        raise UserError(f"the two rigs have no camera name in common ({', '.join(a.names)} vs "
                        f"{', '.join(b.names)})")
    cams_a = [a[name] for name in common]
    cams_b = [b[name] for name in common]
    fitted = similarity_from_rigs(cams_a, cams_b) if len(common) >= 2 else None
    if align and (scale and fitted is not None):
        R, t, s = fitted
    elif align:
        R, t, s = similarity_from_rigs(cams_a, cams_b, scale=False)
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
    grid = grid_points(rig_a)
    rms, n, gross = grid_rms_mm(rig_a, rig_b, grid)
    scale_fig = scale_figures(None if fitted is None else fitted[2], grid)
    scale_fig["applied"] = bool(align and scale and fitted is not None)
    return {
        "cameras": rows,
        "grid_rms_mm": rms,
        "grid_points": n,
        "grid_gross_points": gross,
        "alignment": {"applied": bool(align), "with_scale": scale_fig["applied"],
                      "rotation_deg": _angle_deg(R),
                      "rotation_vector": rvec_from_rotation(R).tolist(),
                      "translation_m": np.asarray(t, dtype=float).tolist(), "scale": float(s)},
        "scale": scale_fig,
        "verdict": verdict(rms, gross, scale_fig["grid_rms_mm"]),
        "only_in_a": [n_ for n_ in a.names if n_ not in set(common)],
        "only_in_b": [n_ for n_ in b.names if n_ not in set(common)],
    }
