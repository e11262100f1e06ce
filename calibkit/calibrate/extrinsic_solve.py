"""Camera poses from the identified projector dots: per-camera PnP, then all cameras at once.

Each camera's dots are world points on the floor or the table top (from the plane maps),
so a camera's pose is a PnP problem: RANSAC on every dot (a misnamed dot is an outlier),
Levenberg-Marquardt on the inliers, inliers again by the refined pose's residuals. The
dots are shared between cameras, so a joint refinement (calibkit.calibrate.bundle) then
makes the cameras agree on them, each dot held on its plane and near its mapped position
by the tape's uncertainty. Cameras that cannot be placed are left out with a message the
user can act on.

The table's height is a scale in z: 10 mm off (1.3 %) moves cameras 4 m away by 15 mm.
The dots measure it too: with the table dots left free, the cameras that agree on the floor
dots triangulate the table top, as well as the floor map knows its own scale (the tape's
error over the reference points' spread: about 1 mm). The two measures are independent, so
their mean weighted by their uncertainties is the best estimate of the true height, and
that is what the dots file carries for solves that bring their own scale (the wand).
These poses, though, live in the floor map's frame, and the dots' figure carries that
map's scale error: within the tape's stated error it placed the cameras no better than the
tape alone (measured: docs/extrinsic.md). So the poses use the tape's height unless the
two disagree beyond both uncertainties: then the tape is taken for a misreading, the
poses use the weighted height too, and the user is told to re-measure.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import cv2
import numpy as np

from calibkit.calibrate import bundle
from calibkit.calibrate.extrinsic_capture import DotObservations
from calibkit.calibrate.extrinsic_reference import FLOOR, TABLE, PlaneMap
from calibkit.calibrate.extrinsic_report import figures
from calibkit.core.camera import Camera, Rig
from calibkit.core.errors import UserError


@dataclass(frozen=True)
class SolveOptions:
    min_dots: int = 12  # fewer dots than this: the camera is not calibrated
    min_table_dots: int = 6  # fewer table dots: "one plane only" warning
    ransac_px: float = 3.0
    outlier_sigmas: float = 4.0
    joint: bool = True  # refine all cameras together on the shared dots
    reference_sigma_m: float = 0.005  # how well the plane maps place a dot (joint solve)
    height_sigma_m: float = 0.002  # how well the table height is known (joint solve)
    refine_height: bool = True  # check the tape's table height against the dots' own
    min_height_dots: int = 10  # table dots seen by two cameras needed to measure the height
    height_check_sigmas: float = 3.0  # tape and dots further apart: the tape misread


@dataclass(frozen=True, eq=False)
class PoseResult:
    """One camera's pose solve: the camera (None if not calibrated), which of its rows were
    inliers, the figures and, when something is wrong, a message for the user."""

    name: str
    camera: Camera | None
    inlier: np.ndarray
    rms_px: float
    floor_dots: int
    table_dots: int
    warning: str = ""


def _pnp(cam: Camera, xyz: np.ndarray, uv: np.ndarray, opts: SolveOptions
         ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """RANSAC on every dot, then Levenberg-Marquardt on the inliers, then inliers again by
    the refined pose's residuals: (rvec, t, inlier mask)."""
    K, dist = cam.K, cam.dist
    obj = np.ascontiguousarray(xyz, np.float64)
    img = np.ascontiguousarray(uv, np.float64)
    ok, rvec, tvec, inl = cv2.solvePnPRansac(obj, img, K, dist, iterationsCount=500,
                                             reprojectionError=opts.ransac_px,
                                             confidence=0.999, flags=cv2.SOLVEPNP_SQPNP)
    if not ok or inl is None or len(inl) < 6:
        return None
    inlier = np.zeros(len(obj), bool)
    inlier[inl.ravel()] = True
    for _ in range(3):
        rvec, tvec = cv2.solvePnPRefineLM(obj[inlier], img[inlier], K, dist, rvec, tvec)
        proj, _ = cv2.projectPoints(obj, rvec, tvec, K, dist)
        r = np.linalg.norm(proj.reshape(-1, 2) - img, axis=1)
        sigma = np.median(r[inlier]) / 1.1774  # a 2D Gaussian's norm has median 1.1774 sigma
        new = r <= max(opts.outlier_sigmas * sigma, 0.5)
        if np.array_equal(new, inlier) or new.sum() < 6:
            break
        inlier = new
    return rvec.ravel(), tvec.ravel(), inlier


def solve_camera(cam: Camera, xyz: np.ndarray, plane: np.ndarray, uv: np.ndarray,
                 opts: SolveOptions = SolveOptions()) -> PoseResult:
    """A camera's pose from its dots (world points (N, 3) on plane ids (N,), pixels)."""
    n_floor, n_table = int(np.sum(plane == FLOOR)), int(np.sum(plane == TABLE))
    none = np.zeros(len(uv), bool)
    if len(uv) < opts.min_dots:
        what = "no projected dot" if len(uv) == 0 else f"only {len(uv)} projected dots"
        return PoseResult(cam.name, None, none, math.nan, n_floor, n_table,
                          f"camera {cam.name} saw {what} (needs {opts.min_dots}): not "
                          "calibrated; turn it towards the floor the projector lights, or "
                          "move the projector so its dots reach the camera's view")
    sol = _pnp(cam, xyz, uv, opts)
    if sol is None:
        return PoseResult(cam.name, None, none, math.nan, n_floor, n_table,
                          f"camera {cam.name}: no pose fits its {len(uv)} dots (are its "
                          "intrinsics right? is the reference-points file for this "
                          "projector?): not calibrated")
    rvec, t, inlier = sol
    solved = cam.replace(rvec=rvec, t=t)
    proj, _ = solved.project(xyz[inlier])
    rms = float(np.sqrt(np.mean(np.sum((proj - uv[inlier]) ** 2, axis=1))))
    fi = int(np.sum(inlier & (plane == FLOOR)))
    ti = int(np.sum(inlier & (plane == TABLE)))
    warning = ""
    if ti < opts.min_table_dots or fi < opts.min_table_dots:
        seen, unseen = ("floor", "table") if ti < opts.min_table_dots else ("table", "floor")
        warning = (f"camera {cam.name} saw the {seen} dots but only "
                   f"{ti if seen == 'floor' else fi} on the {unseen}: calibrated from one "
                   f"plane, less accurate away from it; turn the camera to see the {unseen} "
                   "too (or move the table into its view)")
    return PoseResult(cam.name, solved, inlier, rms, fi, ti, warning)


def _joint(rig: Rig, dots: DotObservations, use: np.ndarray, opts: SolveOptions
           ) -> tuple[Rig, np.ndarray]:
    """All calibrated cameras at once on the shared dots (calibkit.calibrate.bundle): each dot is a
    free point held on its plane (sigma height_sigma_m) and near where the plane maps put it
    (sigma reference_sigma_m), so the cameras must agree with each other, not only with the
    maps. Returns the rig and the refined dot positions (NaN where a dot was not used)."""
    sel = dots.select(use)
    index = np.array([rig.names.index(n) if n in rig.names else -1 for n in dots.camera_names])
    used = np.unique(sel.point[index[sel.camera] >= 0])
    data = bundle_data(rig, sel)
    result = bundle.solve(data, bundle.BundleOptions(
        noise_px=0.3, known_sigma_m=opts.reference_sigma_m, plane_sigma_m=opts.height_sigma_m,
        rounds=1, max_iterations=50))
    refined = np.full_like(dots.xyz, np.nan)
    refined[used] = result.xyz
    return result.rig, refined


@dataclass(frozen=True)
class TableHeight:
    """The table top's height as the tape gave it, as the dots measure it (NaN when too few
    table dots were seen by two cameras), the standard deviation of the dots' figure, both
    weighted by their uncertainties (best_m: the dots file's), and the height the poses
    used (the tape's, or best_m when the two disagree)."""

    tape_m: float
    dots_m: float
    dots_sigma_m: float
    best_m: float
    used_m: float
    disagreement_sigmas: float  # |dots - tape| over both uncertainties combined

    def as_dict(self) -> dict:
        return {"tape_m": self.tape_m, "dots_m": self.dots_m,
                "dots_sigma_mm": self.dots_sigma_m * 1000.0, "best_m": self.best_m,
                "used_m": self.used_m, "disagreement_sigmas": self.disagreement_sigmas}


def measure_table_height(rig: Rig, dots: DotObservations, use: np.ndarray, floor: PlaneMap,
                         tape_m: float, opts: SolveOptions = SolveOptions()) -> TableHeight:
    """The table height from the dots: the joint solve with only the floor dots held (on
    z = 0 and near their mapped places) and the table dots free, so the cameras triangulate
    the table top; its mean z is the dots' height. Its uncertainty is what the floor map
    leaves of the scale (height x the tape's error over the floor references' spread) with
    the dots' own scatter; the tape's is opts.height_sigma_m. best_m is the two weighted;
    used_m is the tape's, or best_m when they are further apart than
    opts.height_check_sigmas of both (the tape misread)."""
    sel = dots.select(use)
    index = np.array([rig.names.index(n) if n in rig.names else -1 for n in dots.camera_names])
    used = np.unique(sel.point[index[sel.camera] >= 0])
    data = bundle_data(rig, sel)
    on_floor = dots.plane[used] == FLOOR
    pts = np.flatnonzero(on_floor)
    held = dataclasses.replace(data, known_point=pts, known_xyz=data.xyz[pts], plane_point=pts,
                               plane_normal=data.plane_normal[pts],
                               plane_offset_m=data.plane_offset_m[pts])
    tape_only = TableHeight(tape_m, math.nan, math.inf, tape_m, tape_m, 0.0)
    if not np.isfinite(floor.spread_m) or np.count_nonzero(~on_floor) < opts.min_height_dots:
        return tape_only
    result = bundle.solve(held, bundle.BundleOptions(
        noise_px=0.3, known_sigma_m=opts.reference_sigma_m, plane_sigma_m=opts.height_sigma_m,
        rounds=1, max_iterations=50))
    z = result.xyz[~on_floor, 2]
    z = z[np.isfinite(z)]
    if len(z) < opts.min_height_dots:
        return tape_only
    dots_m = float(np.mean(z))
    sigma = math.hypot(dots_m * opts.reference_sigma_m / floor.spread_m,
                       float(np.std(z)) / math.sqrt(len(z)))
    w_tape, w_dots = 1.0 / opts.height_sigma_m**2, 1.0 / sigma**2
    apart = abs(dots_m - tape_m) / math.hypot(opts.height_sigma_m, sigma)
    best_m = float((tape_m * w_tape + dots_m * w_dots) / (w_tape + w_dots))
    used_m = tape_m if apart <= opts.height_check_sigmas else best_m
    return TableHeight(tape_m, dots_m, sigma, best_m, used_m, float(apart))


def at_height(dots: DotObservations, height_m: float) -> DotObservations:
    """The dots with the table top at height_m (its dots' z and the plane's height)."""
    xyz = dots.xyz.copy()
    xyz[dots.plane == TABLE, 2] = height_m
    return dataclasses.replace(dots, xyz=xyz, plane_height_m=(dots.plane_height_m[0],
                                                              float(height_m)))


def bundle_data(rig: Rig, dots: DotObservations, known: bool = True):
    """The dots as calibkit.calibrate.bundle input for `rig` (cameras matched by name): every dot a
    point observed by its cameras, held on its plane (n = z, d = height) and, with `known`,
    near its plane-map position (known_point). To join them to a wand solve, append these
    rows (points renumbered after the wand's) to its BundleData."""
    index = np.array([rig.names.index(n) if n in rig.names else -1
                      for n in dots.camera_names])
    rows = index[dots.camera] >= 0
    used, point = np.unique(dots.point[rows], return_inverse=True)
    xyz = dots.xyz[used]
    heights = np.array(dots.plane_height_m)[dots.plane[used]]
    normals = np.tile([0.0, 0.0, 1.0], (len(used), 1))
    pts = np.arange(len(used))
    return bundle.BundleData(
        rig, point, index[dots.camera[rows]], dots.uv[rows], xyz,
        known_point=pts if known else np.zeros(0, np.int64),
        known_xyz=xyz if known else np.zeros((0, 3)),
        plane_point=pts, plane_normal=normals, plane_offset_m=heights)


def join_bundle_data(a, b):
    """Two calibkit.calibrate.bundle.BundleData over the same rig as one: b's points are renumbered
    after a's. This is how the projector's dots (bundle_data) join a wand solve: their
    plane and position priors then hold the world frame while the wand refines the rest."""
    if a.rig.names != b.rig.names:
        raise ValueError("both BundleData must use the same rig (same cameras, same order)")
    n = len(a.xyz)
    cat = np.concatenate
    return bundle.BundleData(
        a.rig, cat([a.obs_point, b.obs_point + n]), cat([a.obs_camera, b.obs_camera]),
        cat([a.obs_uv, b.obs_uv]), cat([a.xyz, b.xyz]),
        cat([a.edge, b.edge + n]).reshape(-1, 2), cat([a.edge_length_m, b.edge_length_m]),
        cat([a.known_point, b.known_point + n]), cat([a.known_xyz, b.known_xyz]),
        cat([a.plane_point, b.plane_point + n]), cat([a.plane_normal, b.plane_normal]),
        cat([a.plane_offset_m, b.plane_offset_m]))


@dataclass(eq=False)
class ExtrinsicResult:
    rig: Rig  # the calibrated cameras only
    poses: list[PoseResult]
    dots: DotObservations  # every identified dot (all cameras)
    inlier: np.ndarray  # (len(dots),) rows used
    refined_xyz: np.ndarray  # (P, 3) dots after the joint solve (plane-map points without it)
    report: dict
    warnings: list[str]


def calibrate(intrinsics: Rig, dots: DotObservations, floor: PlaneMap,
              table: PlaneMap | None, opts: SolveOptions = SolveOptions()) -> ExtrinsicResult:
    """Every camera's pose from its dots; cameras that cannot be placed are left out with
    a warning. Raises UserError when none can be placed."""
    absent = [n for n in dots.camera_names if n not in intrinsics.names]
    if absent:
        raise UserError(f"camera '{absent[0]}' has no intrinsics in the rig file (it has "
                        f"{', '.join(intrinsics.names)})")
    poses, messages = [], []
    if table is None:
        opts = dataclasses.replace(opts, min_table_dots=0)
        messages.append("no table: every camera is calibrated from the floor alone, less "
                        "accurate at head height; add the table (docs/extrinsic.md)")
    inlier = np.zeros(len(dots), bool)
    for c, name in enumerate(dots.camera_names):
        rows = np.flatnonzero(dots.camera == c)
        p = dots.point[rows]
        res = solve_camera(intrinsics[name], dots.xyz[p], dots.plane[p], dots.uv[rows], opts)
        poses.append(res)
        inlier[rows[res.inlier]] = True
        if res.warning:
            messages.append(res.warning)
    placed = [r.camera for r in poses if r.camera is not None]
    if not placed:
        why = ", ".join(f"{r.name} {r.warning.split(': ')[0].split(' ', 2)[2]}"
                        .replace(f" (needs {opts.min_dots})", "") for r in poses)
        raise UserError(f"no camera could be calibrated ({why}): each needs "
                        f"{opts.min_dots} identified dots; turn the cameras towards the "
                        "floor the projector lights, and check --intrinsics and --refs")
    rig = Rig(tuple(placed))
    refined = dots.xyz
    height = None
    if opts.joint and len(placed) >= 2:
        if table is not None and opts.refine_height:
            height = measure_table_height(rig, dots, inlier, floor, table.height_m, opts)
            dots = at_height(dots, height.used_m)
            table = dataclasses.replace(table, height_m=height.used_m)
            if height.disagreement_sigmas > opts.height_check_sigmas:
                messages.append(
                    f"the table dots put the table top at {1000 * height.dots_m:.1f} mm, the "
                    f"tape at {1000 * height.tape_m:.1f} mm ({height.disagreement_sigmas:.1f} "
                    f"times their uncertainties apart): used {1000 * height.used_m:.1f} mm; "
                    "re-measure the table's height at its corners (is the top level? is "
                    "height_m in metres?)")
        rig, refined = _joint(rig, dots, inlier, opts)
        poses = [_refigure(r, rig) for r in poses]
    report = figures(rig, poses, dots, inlier, floor, table, refined)
    report["table_height"] = None if height is None else height.as_dict()
    if height is not None:
        dots = at_height(dots, height.best_m)  # for solves with their own scale
    meta = {"source": "calibkit extrinsic --projector", "world_frame": "projector floor"}
    quality = {"extrinsic": {
        "reprojection_rms_px": report["reprojection_rms_px"],
        "mean_ray_distance_mm": report["mean_ray_distance_mm"],
        "mean_ray_distance_table_mm": report["mean_ray_distance_table_mm"],
        "floor_residual_rms_mm": floor.residual_rms_mm}}
    rig = Rig(rig.cameras, quality, {**{k: v for k, v in intrinsics.meta.items()
                                        if k in ("volume_m",)}, **meta})
    report["warnings"] = messages
    return ExtrinsicResult(rig, poses, dots, inlier, refined, report, messages)


def _refigure(res: PoseResult, rig: Rig) -> PoseResult:
    if res.camera is None:
        return res
    return PoseResult(res.name, rig[res.name], res.inlier, res.rms_px, res.floor_dots,
                      res.table_dots, res.warning)
