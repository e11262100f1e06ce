"""The intrinsic step's target views (a monitor's dots) as factors of the wand's graph: one
pose per view, the dots held at their known places, every sighting through the camera's
shared Cal3DS2.

Why one factor per view, vectorised, and not one built-in factor per dot: the dots are
known, so a built-in projection factor would need each as a variable (GeneralSFMFactor2
takes the point as one), and eliminating thousands of dot variables, each tied to every
view of its camera and to its Cal3DS2, cost ~8x the wand's own solve. A view's factor
touches only its pose and its camera's Cal3DS2: numpy projects its ~1000 dots and gives the
exact Jacobians at once, and GTSAM sees a few dozen small factors.

GTSAM's conventions: a view's pose is the camera in the target's frame (camera-to-target);
Pose3 is perturbed on the right, pose * Exp([w, v]); Cal3DS2 (fx fy skew cx cy k1 k2 p1 p2)
is perturbed by adding to that vector. Residuals are predicted minus observed pixels.
"""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np

from calibkit.core.camera import Rig
from calibkit.core.geometry import RigArrays

V = gtsam.symbol_shorthand.V  # target views: the camera's pose in the target's frame


@dataclass(eq=False)
class TargetData:
    """The intrinsic step's views of a flat target for the cameras of a BundleData: rows
    (camera, view, pixel) with each dot's known place in the target's frame, and each
    view's starting pose (target-to-camera, as the intrinsic step solved it)."""

    obs_camera: np.ndarray  # (M,) int, the bundle's camera index
    obs_view: np.ndarray  # (M,) int
    obs_xyz: np.ndarray  # (M, 3) metres, target frame
    obs_uv: np.ndarray  # (M, 2) distorted pixels
    view_R: np.ndarray  # (V, 3, 3) target-to-camera
    view_t: np.ndarray  # (V, 3)

    def __len__(self) -> int:
        return len(self.obs_uv)

    def replace(self, **kw) -> TargetData:
        return TargetData(**{**self.__dict__, **kw})


def view_cameras(target: TargetData) -> np.ndarray:
    """The camera of each view."""
    cam = np.zeros(len(target.view_R), dtype=np.int64)
    cam[target.obs_view] = target.obs_camera
    return cam


def _view_arrays(rig: Rig, target: TargetData) -> RigArrays:
    """Each view as a camera: its camera's intrinsics, the view's pose."""
    a = RigArrays.from_rig(rig)
    cam = view_cameras(target)
    centre = -np.einsum("vji,vj->vi", target.view_R, target.view_t)
    return RigArrays(target.view_R, target.view_t, centre, a.fx[cam], a.fy[cam], a.cx[cam],
                     a.cy[cam], a.skew[cam], a.dist[cam])


def residuals(rig: Rig, target: TargetData) -> np.ndarray:
    """Observed minus projected pixels (M, 2); NaN behind the camera."""
    proj, z = _view_arrays(rig, target).project(target.obs_view, target.obs_xyz)
    r = target.obs_uv - proj
    r[~(z > 0)] = np.nan
    return r


def _project(pose: gtsam.Pose3, cal: gtsam.Cal3DS2, xyz: np.ndarray, jacobians: bool):
    """Pixels of target points through one view, and d pixels / d (pose tangent, Cal3DS2)
    as (N, 2, 6) and (N, 2, 9) when asked."""
    Rwc = pose.rotation().matrix()  # camera-to-target
    pc = (xyz - pose.translation()) @ Rwc  # R^T (X - t), row-wise
    fx, fy, s, u0, v0, k1, k2, p1, p2 = cal.vector()
    z = pc[:, 2]
    x, y = pc[:, 0] / z, pc[:, 1] / z
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * k2)
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    uv = np.stack([fx * xd + s * yd + u0, fy * yd + v0], axis=1)
    if not jacobians:
        return uv, None, None
    n = len(pc)
    # d (xd, yd) / d (x, y)
    dr = k1 + 2.0 * k2 * r2
    j11 = radial + 2.0 * x * x * dr + 2.0 * p1 * y + 6.0 * p2 * x
    j12 = 2.0 * x * y * dr + 2.0 * p1 * x + 2.0 * p2 * y
    j22 = radial + 2.0 * y * y * dr + 6.0 * p1 * y + 2.0 * p2 * x
    a11, a12, a21, a22 = fx * j11 + s * j12, fx * j12 + s * j22, fy * j12, fy * j22
    inv_z = 1.0 / z
    d_pc = np.empty((n, 2, 3))  # d uv / d pc
    d_pc[:, 0, 0], d_pc[:, 0, 1] = a11 * inv_z, a12 * inv_z
    d_pc[:, 0, 2] = -(a11 * x + a12 * y) * inv_z
    d_pc[:, 1, 0], d_pc[:, 1, 1] = a21 * inv_z, a22 * inv_z
    d_pc[:, 1, 2] = -(a21 * x + a22 * y) * inv_z
    # pose * Exp([w, v]) moves pc by pc x w - v
    skew_pc = np.zeros((n, 3, 3))
    skew_pc[:, 0, 1], skew_pc[:, 0, 2] = -pc[:, 2], pc[:, 1]
    skew_pc[:, 1, 0], skew_pc[:, 1, 2] = pc[:, 2], -pc[:, 0]
    skew_pc[:, 2, 0], skew_pc[:, 2, 1] = -pc[:, 1], pc[:, 0]
    d_pose = np.concatenate([d_pc @ skew_pc, -d_pc], axis=2)
    # Cal3DS2: fx fy skew cx cy k1 k2 p1 p2
    d_cal = np.zeros((n, 2, 9))
    d_cal[:, 0, 0], d_cal[:, 1, 1], d_cal[:, 0, 2] = xd, yd, yd
    d_cal[:, 0, 3], d_cal[:, 1, 4] = 1.0, 1.0
    for k, (dx, dy) in enumerate(((x * r2, y * r2), (x * r2 * r2, y * r2 * r2),
                                  (2.0 * x * y, r2 + 2.0 * y * y),
                                  (r2 + 2.0 * x * x, 2.0 * x * y))):
        d_cal[:, 0, 5 + k] = fx * dx + s * dy
        d_cal[:, 1, 5 + k] = fy * dy
    return uv, d_pose, d_cal


def _view_factor(view_key: int, cal_key: int, xyz: np.ndarray, uv: np.ndarray,
                 sigma_px: float) -> gtsam.CustomFactor:
    """One view's dots as one factor on (its pose, its camera's Cal3DS2)."""
    measured = uv.ravel()

    def error(this, values, H):
        pose, cal = values.atPose3(view_key), values.atCal3DS2(cal_key)
        pred, d_pose, d_cal = _project(pose, cal, xyz, H is not None)
        if H is not None:
            H[0] = d_pose.reshape(-1, 6)
            H[1] = d_cal.reshape(-1, 9)
        return pred.ravel() - measured

    noise = gtsam.noiseModel.Isotropic.Sigma(len(measured), float(sigma_px))
    return gtsam.CustomFactor(noise, [view_key, cal_key], error)


def add_factors(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, target: TargetData,
                use: np.ndarray | None, noise_px: np.ndarray, cal_key) -> None:
    """Every view with rows in `use` as a factor (its camera's pixels with that camera's
    noise `noise_px`), and its pose as a starting value. Outliers are dropped between rounds
    by the caller (a whole view's factor cannot be robust per dot)."""
    use = np.ones(len(target), dtype=bool) if use is None else use
    order = np.argsort(target.obs_view, kind="stable")
    order = order[use[order]]
    views, start = np.unique(target.obs_view[order], return_index=True)
    cams = view_cameras(target)
    for v, rows in zip(views.tolist(), np.split(order, start[1:]), strict=True):
        sigma = noise_px[cams[v]]
        if len(rows) < 3 or not np.isfinite(sigma) or sigma <= 0:
            continue
        R = target.view_R[v]
        values.insert(V(v), gtsam.Pose3(gtsam.Rot3(R.T), -R.T @ target.view_t[v]))
        graph.add(_view_factor(V(v), cal_key(int(cams[v])), target.obs_xyz[rows],
                               target.obs_uv[rows], sigma))


def read_views(result: gtsam.Values, target: TargetData) -> TargetData:
    """The views' solved poses (views not in the graph keep their start)."""
    R, t = target.view_R.copy(), target.view_t.copy()
    for v in range(len(R)):
        if result.exists(V(v)):
            pose = result.atPose3(V(v))
            R[v] = pose.rotation().matrix().T
            t[v] = -R[v] @ pose.translation()
    return target.replace(view_R=R, view_t=t)
