"""How well a wand capture determines the shape of the space it reconstructs: the grid RMS
the solve's own covariance predicts, and how much of it the intrinsics' uncertainty adds.

Why this figure: refined from the wand alone, intrinsics are known only as well as the
capture pins them, and the weak directions mix the distortion terms, the principal points,
the focal lengths and the cameras' turns (a principal point and a small turn of the camera
look alike but for the distortion about it; see docs/wand.md). Camera position standard
deviations show it badly (a camera's distance along its axis trades against its focal
length at little cost to the reconstructed space), the residuals not at all (the fit is as
good either way). What a user feels is the error of a point triangulated in the volume,
so that is what this predicts: a grid filling the box the wand went through is
triangulated with the solved rig, the derivatives of every grid point by every camera
parameter (poses and, when refined, fx fy cx cy k1 k2 p1 p2) are taken numerically, and
the joint marginal covariance of those parameters (gauge held at the reference camera) is
carried through them. The similarity any wand calibration is free in (3 translations, 3
rotations, the scale, which the wand's length and the floor set apart) is projected out,
as calibkit compare aligns.
Conditioning the covariance on the intrinsics gives the same figure had the intrinsics
been known exactly: the difference is what only other views of the cameras (the monitor's)
or intrinsics given with their uncertainty can rule out.

It is a first-order prediction for the noise the solve estimated: the RMS over the grid,
one standard deviation, not a bound on any single capture's error (which is one draw), and
blind to what is wrong beyond the noise (intrinsics held at wrong values, a biased monitor
calibration): on the simulator the error against the truth was 0.7-0.9 times it where
only noise was at work (benchmarks/bench_wand_shape.py).
"""

from __future__ import annotations

import gtsam
import numpy as np

from calibkit.calibrate import bundle
from calibkit.calibrate.compare import seen_by_two
from calibkit.core.camera import Camera, Rig, rotation_from_rvec
from calibkit.core.geometry import triangulate

GRID_STEPS = 8  # grid points per axis over the wand's box (512 before visibility)
BOX_PERCENTILES = (2.0, 98.0)  # the box the wand went through, its stray points left out
STEP_RAD = 1e-6  # finite-difference step for rotations (rad), and metres for positions
STEP_REL = 1e-6  # ... and relative to each intrinsic's size (at least 1e-6 absolute)
INTRINSICS = (0, 1, 3, 4, 5, 6, 7, 8)  # Cal3DS2 fx fy cx cy k1 k2 p1 p2 (skew held)
NAMES = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2")
# which views would rule the rest out: the figure had each group been known in every camera
GROUPS = {"focal": ("fx", "fy"), "principal_point": ("cx", "cy"),
          "distortion": ("k1", "k2", "p1", "p2")}
# the intrinsics' part of the shape uncertainty worth a warning: this many times what it
# would be with them known, and at least this many millimetres
DOMINANT_RATIO = 2.0
DOMINANT_MM = 0.05


def wand_grid(rig: Rig, xyz: np.ndarray, steps: int = GRID_STEPS) -> np.ndarray:
    """Points filling the box the solved wand points span (2-98 percentiles per axis) that
    two or more cameras of `rig` see: where this capture can vouch for the space."""
    pts = xyz[np.isfinite(xyz).all(axis=1)]
    if len(pts) < 2:
        return np.zeros((0, 3))
    lo, hi = np.percentile(pts, BOX_PERCENTILES, axis=0)
    return seen_by_two(rig, lo, hi, steps)


def _views(rig: Rig, grid: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    point, camera, uv = [], [], []
    for c, cam in enumerate(rig):
        px, front = cam.project(grid)
        vis = np.flatnonzero(front & cam.in_image(px))
        point.append(vis)
        camera.append(np.full(len(vis), c))
        uv.append(px[vis])
    return np.concatenate(point), np.concatenate(camera), np.concatenate(uv)


def _perturbed(cam: Camera, j: int, h: float) -> Camera:
    """The camera moved along parameter j of the graph's tangent space: 0-2 a turn about its
    own axes, 3-5 a shift along them (GTSAM's Pose3, camera-to-world, body frame), 6-13
    fx fy cx cy k1 k2 p1 p2."""
    if j < 3:
        w = np.zeros(3)
        w[j] = h
        R_wc = cam.R.T @ rotation_from_rvec(w)
        return cam.replace(R=R_wc.T, t=-R_wc.T @ cam.centre)
    if j < 6:
        v = np.zeros(3)
        v[j - 3] = h
        return cam.replace(t=-cam.R @ (cam.centre + cam.R.T @ v))
    name = ("fx", "fy", "cx", "cy")[j - 6] if j < 10 else None
    if name is not None:
        return cam.replace(**{name: getattr(cam, name) + h})
    dist = np.array(cam.dist, dtype=np.float64)
    dist[j - 10] += h
    return cam.replace(dist=dist)


def _jacobian(rig: Rig, grid: np.ndarray, refined: bool) -> tuple[np.ndarray, np.ndarray]:
    """d(grid points)/d(parameters), (3 G, P) with P = 6 (+ 8) per camera in the order of
    the joint covariance (all poses, then all intrinsics), and the points that triangulate."""
    point, camera, uv = _views(rig, grid)
    base = triangulate(rig, point, camera, uv, n_points=len(grid), ray_distance=False).xyz
    ok = np.isfinite(base).all(axis=1)
    n = len(rig)
    cols = [(c, j) for c in range(n) for j in range(6)]
    if refined:
        cols += [(c, 6 + j) for c in range(n) for j in range(8)]
    J = np.zeros((3 * int(ok.sum()), len(cols)))
    for col, (c, j) in enumerate(cols):
        value = (rig[c].fx, rig[c].fy, rig[c].cx, rig[c].cy, *rig[c].dist[:4])[j - 6] \
            if j >= 6 else 0.0
        h = STEP_RAD if j < 6 else max(1e-6, STEP_REL * abs(value))
        moved = Rig(tuple(_perturbed(cam, j, h) if k == c else cam
                          for k, cam in enumerate(rig)))
        # the same pixels through the moved camera, refined from where they were
        xyz = triangulate(moved, point, camera, uv, n_points=len(grid), ray_distance=False,
                          start=np.where(ok[:, None], base, 0.0)).xyz
        J[:, col] = ((xyz - base)[ok] / h).ravel()
    return J, ok


def _without_similarity(J: np.ndarray, grid: np.ndarray) -> np.ndarray:
    """J with the grid's translations, rotations and scale projected out."""
    g = grid - grid.mean(axis=0)
    modes = []
    for a in range(3):
        e = np.zeros(3)
        e[a] = 1.0
        modes.append(np.broadcast_to(e, g.shape).ravel())
        modes.append(np.cross(e, g).ravel())
    modes.append(g.ravel())
    Q, _ = np.linalg.qr(np.array(modes).T)
    return J - Q @ (Q.T @ J)


def _joint_covariance(result: bundle.BundleResult) -> np.ndarray:
    """The joint marginal covariance of every camera's pose (and Cal3DS2 when refined, skew
    dropped) with the gauge held tightly at the reference camera, as camera_covariances."""
    data, options = result.data, result.options
    k3_free = Rig(tuple(c.replace(dist=c.dist * [1, 1, 1, 1, 0]) for c in result.rig))
    graph, values, _ = bundle.build_graph(
        data, data.obs_uv, result.inlier, result.noise_px, options, result.xyz, k3_free,
        tight_gauge=True, prior_rig=data.rig, target=result.target,
        target_use=result.target_inlier, target_noise_px=result.target_noise_px,
        robust=options.rounds <= options.robust_rounds)
    n = len(result.rig)
    keys = gtsam.KeyVector()
    for c in range(n):
        keys.append(bundle.X(c))
    if options.refine_intrinsics:
        for c in range(n):
            keys.append(bundle.K(c))
    S = gtsam.Marginals(graph, values).jointMarginalCovariance(keys).fullMatrix()
    if not options.refine_intrinsics:
        return S
    keep = np.r_[np.arange(6 * n), 6 * n + (9 * np.arange(n)[:, None] +
                                            np.array(INTRINSICS)).ravel()]
    return S[np.ix_(keep, keep)]


def shape_uncertainty(result: bundle.BundleResult, unit_m: float = 1.0) -> dict:
    """The grid RMS (mm, one sigma, similarity removed) the solve's covariance predicts over
    the box the wand went through; with refined intrinsics also the same had they been known
    exactly, and the part they add. unit_m: metres per unit of the solve. Raises
    RuntimeError (GTSAM) where the marginals fail."""
    rig = Rig(tuple(c.replace(dist=c.dist * [1, 1, 1, 1, 0]) for c in result.rig))
    grid = wand_grid(rig, result.xyz)
    refined = bool(result.options.refine_intrinsics)
    if len(grid) < 8:
        return {"grid_rms_mm": float("nan"), "grid_points": int(len(grid)),
                "intrinsics_refined": refined,
                "reason": "too few points of the wand's box are seen by two cameras"}
    S = _joint_covariance(result)
    J, ok = _jacobian(rig, grid, refined)
    Jp = _without_similarity(J, grid[ok])
    n_pts = int(ok.sum())

    def rms_mm(cov: np.ndarray, cols: np.ndarray) -> float:
        A = Jp[:, cols]
        return float(np.sqrt(max(np.einsum("ij,jk,ik->", A, cov, A), 0.0) / n_pts)
                     * 1000.0 * unit_m)

    out = {"grid_rms_mm": rms_mm(S, np.arange(len(S))), "grid_points": n_pts,
           "intrinsics_refined": refined}
    def given(fixed: np.ndarray) -> float:  # the figure with the parameters `fixed` known
        free = np.setdiff1d(np.arange(len(S)), fixed)
        cond = S[np.ix_(free, free)] - S[np.ix_(free, fixed)] @ np.linalg.solve(
            S[np.ix_(fixed, fixed)], S[np.ix_(fixed, free)])
        return rms_mm(cond, free)

    if refined:
        intr = np.arange(6 * len(rig), len(S))
        std = np.sqrt(np.clip(np.diag(S)[intr], 0, None)).reshape(len(rig), len(INTRINSICS))
        out["intrinsic_std"] = {cam.name: dict(zip(NAMES, row.tolist(), strict=True))
                                for cam, row in zip(rig, std, strict=True)}
        out["intrinsics_known_mm"] = given(intr)
        out["if_known_mm"] = {
            group: given(6 * len(rig) + (len(NAMES) * np.arange(len(rig))[:, None] + np.array(
                [NAMES.index(p) for p in params])).ravel())
            for group, params in GROUPS.items()}
        out["intrinsics_part_mm"] = float(np.sqrt(max(
            out["grid_rms_mm"] ** 2 - out["intrinsics_known_mm"] ** 2, 0.0)))
    return out


def section(result: bundle.BundleResult, unit_m: float = 1.0,
            if_refined: bundle.BundleResult | None = None) -> tuple[dict, list[str]]:
    """The report's `shape_uncertainty` and its warnings. `if_refined`: the solve with every
    camera's intrinsics refined, where the default kept some as given (wand_intrinsics): what
    the capture alone would have left, and the intrinsics' standard deviations it gives, the
    error in them this capture cannot rule out."""
    try:
        out = shape_uncertainty(result, unit_m)
        alt = shape_uncertainty(if_refined, unit_m) if if_refined is not None else None
    except (RuntimeError, np.linalg.LinAlgError) as exc:  # an indeterminate system
        return {"grid_rms_mm": float("nan"),
                "reason": f"no uncertainty: the marginals failed ({str(exc).splitlines()[0]})"
                }, []
    warnings = []
    part, known = out.get("intrinsics_part_mm", 0.0), out.get("intrinsics_known_mm", 0.0)
    if part > max(DOMINANT_RATIO * known, DOMINANT_MM):
        warnings.append(
            f"the wand alone determines the cameras' intrinsics only so far: refined from "
            f"this capture they leave {out['grid_rms_mm']:.3f} mm RMS of shape uncertainty "
            f"over the wand's volume ({known:.3f} mm were they known exactly); the monitor's "
            "views (calibkit intrinsic, then the wand with its rig file) or intrinsics given "
            "with their uncertainties would rule the rest out")
    if alt is not None:
        out["if_refined_mm"] = alt["grid_rms_mm"]
        out["cannot_rule_out"] = alt.get("intrinsic_std", {})
        if not result.options.refine_intrinsics:
            out["note"] = (
                f"{out['grid_rms_mm']:.3f} mm takes the intrinsics kept as given to be exact; "
                f"refined from this capture alone it would be {alt['grid_rms_mm']:.3f} mm, "
                "and an error in them within the standard deviations of `cannot_rule_out` "
                "would not show in its residuals")
    return out, warnings
