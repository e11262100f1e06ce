"""The world frame from the floor: an L-frame of 3 markers, the wand laid on the floor in
two places, or points known to lie on the floor (the projector's dots).

A wand solve knows the rig only up to a rigid motion; users want z up and the floor at
z = 0, as commercial systems do with a square laid on the floor. Every function here
returns a rigid transform (A, b), new = A @ old + b, with A a proper rotation, which
`transform_rig` applies to the cameras. Marker centres sit one marker radius above the
floor, which the L-frame and wand frames subtract.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

from calibkit.core.camera import Rig
from calibkit.core.errors import UserError
from calibkit.core.geometry import triangulate
from calibkit.vision.correspondence import match_frames

LFRAME_MARKER_RADIUS_M = 0.007  # a 14 mm ball: its centre stands this high over the floor


@dataclass(frozen=True)
class LFrame:
    """Three markers on the floor: the corner, one at the end of the long arm (+x), one at
    the end of the short arm (+y). Distances are marker centre to marker centre, metres."""

    long_m: float = 0.5
    short_m: float = 0.3
    marker_height_m: float = LFRAME_MARKER_RADIUS_M

    def points(self, origin=(0.0, 0.0), yaw_rad: float = 0.0) -> np.ndarray:
        """The three marker centres (corner, long, short) in a world frame, for simulation."""
        c, s = np.cos(yaw_rad), np.sin(yaw_rad)
        ox, oy = origin
        h = self.marker_height_m
        return np.array([[ox, oy, h], [ox + self.long_m * c, oy + self.long_m * s, h],
                         [ox - self.short_m * s, oy + self.short_m * c, h]])


def transform_rig(rig: Rig, A: np.ndarray, b: np.ndarray) -> Rig:
    """The rig in the new world frame: x_cam = R x_old + t = R A^T (x_new - b) + t."""
    cams = []
    for cam in rig:
        R = cam.R @ A.T
        cams.append(cam.replace(R=R, t=cam.t - R @ b))
    return Rig(tuple(cams), dict(rig.quality), dict(rig.meta))


def transform_points(xyz: np.ndarray, A: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.asarray(xyz, dtype=np.float64) @ A.T + b


def _frame(origin: np.ndarray, x_dir: np.ndarray, z_dir: np.ndarray,
           height_m: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """(A, b) for a frame at `origin` (lowered by height_m along z) with axes x, z."""
    z = z_dir / np.linalg.norm(z_dir)
    x = x_dir - (x_dir @ z) * z
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    A = np.stack([x, y, z])
    origin = origin - height_m * z
    return A, -A @ origin


def _up_from_cameras(rig: Rig, point: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """The normal's sign that puts the cameras above the plane through `point`."""
    side = (rig.centres() - point) @ normal
    return normal if np.median(side) >= 0 else -normal


def frame_from_lframe(corner: np.ndarray, long_end: np.ndarray, short_end: np.ndarray,
                      lframe: LFrame = LFrame()) -> tuple[np.ndarray, np.ndarray]:
    """Corner at the origin, long arm +x, z = x cross short arm (up when laid as drawn)."""
    x = long_end - corner
    z = np.cross(x, short_end - corner)
    return _frame(corner, x, z, lframe.marker_height_m)


def find_lframe(xyz: np.ndarray, lframe: LFrame = LFrame(),
                tol_m: float = 0.01) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The (corner, long end, short end) among reconstructed points: the one triple whose
    sides fit the L's long arm, short arm and hypotenuse within tol_m."""
    xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    hyp = float(np.hypot(lframe.long_m, lframe.short_m))
    found = []
    for i, j, k in itertools.permutations(range(len(xyz)), 3):
        if (abs(np.linalg.norm(xyz[j] - xyz[i]) - lframe.long_m) <= tol_m
                and abs(np.linalg.norm(xyz[k] - xyz[i]) - lframe.short_m) <= tol_m
                and abs(np.linalg.norm(xyz[k] - xyz[j]) - hyp) <= tol_m):
            found.append((i, j, k))
    if not found:
        raise UserError(f"no L-frame ({lframe.long_m:g} m x {lframe.short_m:g} m) among the "
                        f"{len(xyz)} markers seen: check --long/--short and that at least two "
                        "cameras see all three markers")
    if len(found) > 1:
        raise UserError("more than one set of markers fits the L-frame: take other markers "
                        "out of the volume")
    i, j, k = found[0]
    return xyz[i], xyz[j], xyz[k]


def static_markers(rig: Rig, obs, min_frames: int = 3, cluster_m: float = 0.01) -> np.ndarray:
    """Markers standing still (an L-frame on the floor): matched per frame, then the points
    of all frames grouped by position and averaged (medians), ghosts seen rarely dropped."""
    pts = match_frames(rig, obs)
    xyz = pts.xyz[np.isfinite(pts.xyz).all(axis=1)]
    if not len(xyz):
        raise UserError("no marker is seen by two cameras: check the rig and the recording")
    # deferred on purpose: loads SciPy's clustering, SciPy's sparse graphs... only where used
    from scipy.cluster.hierarchy import fcluster, linkage

    if len(xyz) == 1:
        return xyz
    sample = xyz[:: max(1, len(xyz) // 4000)]
    labels = fcluster(linkage(sample, "single"), cluster_m, criterion="distance")
    n = np.bincount(labels)
    keep = np.flatnonzero(n >= min(min_frames, max(1, len(np.unique(pts.frame)))))
    return np.array([np.median(sample[labels == lab], axis=0) for lab in keep])


def frame_from_wand_on_floor(placements: list[tuple[np.ndarray, np.ndarray]], rig: Rig,
                             marker_height_m: float = LFRAME_MARKER_RADIUS_M
                             ) -> tuple[np.ndarray, np.ndarray]:
    """The wand laid on the floor in two or more places (not parallel): the floor is the
    plane through all of them; marker 0 of the first placement is the origin and the first
    placement points along +x. placements: (marker-0 end, far end) positions."""
    if len(placements) < 2:
        raise UserError("lay the wand on the floor in at least two places (one line does not "
                        "fix the floor's tilt)")
    ends = np.array([p for pair in placements for p in pair])
    d0 = placements[0][1] - placements[0][0]
    dirs = np.array([b - a for a, b in placements])
    cross = np.linalg.norm(np.cross(d0 / np.linalg.norm(d0), dirs /
                                    np.linalg.norm(dirs, axis=1, keepdims=True)), axis=1)
    if cross.max() < 0.3:
        raise UserError("the wand's placements on the floor are nearly parallel: turn it by "
                        "at least 20 degrees between them")
    centre = ends.mean(axis=0)
    normal = np.linalg.svd(ends - centre)[2][2]
    normal = _up_from_cameras(rig, centre, normal)
    return _frame(placements[0][0], d0, normal, marker_height_m)


def frame_from_plane_points(xyz: np.ndarray, rig: Rig,
                            height_m: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Points on the floor (the projector's dots): z along the fitted plane's normal, towards
    the cameras; the origin beneath the points' middle; x along their longest spread."""
    xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    if len(xyz) < 3:
        raise UserError("at least 3 floor points are needed to find the floor")
    centre = xyz.mean(axis=0)
    _, s, vt = np.linalg.svd(xyz - centre)
    if s[1] < 1e-3 * s[0]:
        raise UserError("the floor points lie on a line: they do not fix the floor")
    normal = _up_from_cameras(rig, centre, vt[2])
    return _frame(centre, vt[0], normal, height_m)


def frame_from_cameras(rig: Rig, xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A provisional frame when nothing on the floor was captured: up is the cameras' mean
    image-up direction (cameras hang upright), the floor at the lowest wand points (the
    wand is never below it), the origin beneath the wand points' middle, and x towards the
    first camera. `calibkit floor` replaces it with a measured one."""
    up = np.mean([-cam.R[1] for cam in rig], axis=0)
    if np.linalg.norm(up) < 1e-6:
        up = np.array([0.0, 0.0, 1.0])
    up /= np.linalg.norm(up)
    pts = xyz[np.isfinite(xyz).all(axis=1)]
    middle = np.median(pts, axis=0) if len(pts) else rig.centres().mean(axis=0)
    low = float(np.percentile((pts - middle) @ up, 1)) if len(pts) else 0.0
    origin = middle + low * up
    x = rig[0].centre - origin
    if np.linalg.norm(x - (x @ up) * up) < 1e-6:
        x = np.cross(up, [0.0, 1.0, 0.0]) if abs(up[1]) < 0.9 else np.cross(up, [1.0, 0, 0])
    return _frame(origin, x, up)


def wand_placements(rig: Rig, obs, spacing_m, cluster_m: float = 0.02
                    ) -> list[tuple[np.ndarray, np.ndarray]]:
    """The wand's (marker-0 end, far end) in each place it lay still on the floor: the wand
    identified per frame, triangulated, and frames grouped by where marker 0 was."""
    # deferred on purpose: loads OpenCV only where used
    from calibkit.calibrate.wand import WandSpec, identify, point_index, wand_lengths
    spec = WandSpec(tuple(spacing_m))
    if spec.n_markers < 2:
        raise UserError("a wand laid on the floor needs 2 or 3 markers")
    names = [n for n in obs.camera_names if n in set(rig.names)]
    if len(names) < 2:
        raise UserError("the floor recording's cameras are not in the rig")
    sub = Rig(tuple(rig[n] for n in obs.camera_names)) if len(names) == len(
        obs.camera_names) else None
    if sub is None:
        raise UserError(f"camera '{[n for n in obs.camera_names if n not in rig.names][0]}' "
                        "of the floor recording is not in the rig")
    w = identify(obs, spec, sub)
    pidx, pinfo = point_index(w, spec.n_markers)
    xyz = triangulate(sub, pidx, w.camera, w.uv, n_points=len(pinfo), ray_distance=False).xyz
    lengths = wand_lengths(xyz, pinfo, spec)
    first = np.flatnonzero(pinfo[:, 1] == 0)
    good = np.isfinite(lengths) & (np.abs(lengths - spec.length_m) < 0.02 * spec.length_m)
    key = pinfo[:, 0] * spec.n_markers + pinfo[:, 1]
    last = np.searchsorted(key, pinfo[first, 0] * spec.n_markers + spec.n_markers - 1)
    a, b = xyz[first[good]], xyz[np.minimum(last[good], len(xyz) - 1)]
    if len(a) < 2:
        raise UserError("the wand on the floor was not seen by two cameras at once")
    # deferred on purpose: loads SciPy's clustering, SciPy's sparse graphs... only where used
    from scipy.cluster.hierarchy import fcluster, linkage

    labels = fcluster(linkage(a, "single"), cluster_m, criterion="distance")
    out = []
    for lab in np.unique(labels)[np.argsort([np.min(np.flatnonzero(labels == x))
                                             for x in np.unique(labels)])]:
        m = labels == lab
        if m.sum() >= 3:
            out.append((np.median(a[m], axis=0), np.median(b[m], axis=0)))
    return out


def world_from_recording(rig: Rig, obs, kind: str = "lframe", lframe: LFrame = LFrame(),
                         spacing_m=(0.0, 0.2, 0.5)) -> tuple[np.ndarray, np.ndarray]:
    """(A, b) from a floor recording made with `rig`: kind 'lframe', 'wand' or 'plane'."""
    if kind == "lframe":
        corner, long_end, short_end = find_lframe(static_markers(rig, obs), lframe)
        return frame_from_lframe(corner, long_end, short_end, lframe)
    if kind == "wand":
        return frame_from_wand_on_floor(wand_placements(rig, obs, spacing_m), rig,
                                        lframe.marker_height_m)
    if kind == "plane":
        return frame_from_plane_points(static_markers(rig, obs), rig)
    raise UserError(f"--kind must be lframe, wand or plane, got {kind!r}")
