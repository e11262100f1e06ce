"""A robot's own trajectory against ours: clock offset and drift, alignment, pose errors.

What a drone lab does with motion capture every day: fly, log the robot's estimate (VIO,
SLAM, an EKF) on its own clock and in its own world frame, then ask how far off it was.
The two logs share neither clock nor frame, so both are estimated first:

1. a coarse clock offset from the cross-correlation of the two speed profiles (speed does
   not depend on the world frame, so this needs no alignment yet);
2. one least-squares fit of offset, clock drift and the SE(3) (or Sim(3)) alignment
   together, the estimate's positions taken at any time from a cubic spline, with a robust
   loss so the estimate's own blunders do not bend it;
3. absolute errors (ATE) after alignment, and relative errors (RPE) over a time step,
   which say how the estimate drifts regardless of the alignment.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.interpolate import CubicSpline
from scipy.optimize import least_squares
from scipy.signal import correlate
from scipy.spatial.transform import Rotation, Slerp

from calibkit.core.errors import UserError
from daemon.formats.trajectory_io import Trajectory

SPEED_WINDOW_S = 0.1  # speeds for the coarse offset are taken over this span (noise)


@dataclass(frozen=True)
class TimeModel:
    """t_estimate = (1 + drift) * t_reference + offset_s."""

    offset_s: float
    drift: float = 0.0

    def to_estimate(self, t_ref: np.ndarray) -> np.ndarray:
        return (1.0 + self.drift) * t_ref + self.offset_s


@dataclass(frozen=True)
class Alignment:
    """reference = scale * R @ estimate + t."""

    R: np.ndarray
    t: np.ndarray
    scale: float = 1.0

    def apply(self, xyz: np.ndarray) -> np.ndarray:
        return self.scale * xyz @ self.R.T + self.t


@dataclass(frozen=True, eq=False)
class Evaluation:
    time: TimeModel
    coarse_offset_s: float
    alignment: Alignment
    body_rotation: np.ndarray  # (3, 3) estimate body -> reference body (identity unless fitted)
    t_s: np.ndarray  # (M,) reference times compared
    ref_xyz: np.ndarray  # (M, 3)
    est_xyz: np.ndarray  # (M, 3) aligned
    position_error_m: np.ndarray  # (M,)
    rotation_error_deg: np.ndarray  # (M,)
    rpe_translation_m: np.ndarray  # (P,)
    rpe_rotation_deg: np.ndarray  # (P,)
    rpe_delta_s: float


def _uniform(traj: Trajectory, dt: float) -> tuple[np.ndarray, np.ndarray]:
    t = np.arange(traj.t_s[0], traj.t_s[-1], dt)
    xyz = np.column_stack([np.interp(t, traj.t_s, traj.xyz[:, k]) for k in range(3)])
    return t, xyz


def _speed(xyz: np.ndarray, dt: float) -> np.ndarray:
    k = max(1, int(round(SPEED_WINDOW_S / dt / 2)))
    v = np.zeros(len(xyz))
    v[k:-k] = np.linalg.norm(xyz[2 * k:] - xyz[:-2 * k], axis=1) / (2 * k * dt)
    return v


def coarse_offset(ref: Trajectory, est: Trajectory, max_offset_s: float) -> float:
    """The clock offset (estimate minus reference) that best lines up the speed profiles,
    to a fraction of a sample (parabola through the correlation peak)."""
    dt = float(min(np.median(np.diff(ref.t_s)), np.median(np.diff(est.t_s)), 0.01))
    t_r, x_r = _uniform(ref, dt)
    t_e, x_e = _uniform(est, dt)
    s_r, s_e = _speed(x_r, dt), _speed(x_e, dt)
    if s_r.std() == 0 or s_e.std() == 0:
        raise UserError("a trajectory does not move: the clocks cannot be lined up")
    s_r = (s_r - s_r.mean()) / s_r.std()
    s_e = (s_e - s_e.mean()) / s_e.std()
    c = correlate(s_e, s_r, mode="full", method="fft")
    lags = np.arange(-(len(s_r) - 1), len(s_e))
    # lag L: estimate sample i + L matches reference sample i, so
    # offset = t_e[0] + L dt - t_r[0]
    offsets = t_e[0] - t_r[0] + lags * dt
    overlap = np.minimum(len(s_e), len(s_r) + lags) - np.maximum(0, lags)
    ok = (np.abs(offsets) <= max_offset_s) & (overlap >= 0.3 * min(len(s_r), len(s_e)))
    if not ok.any():
        raise UserError(f"the trajectories do not overlap in time within --max-offset "
                        f"{max_offset_s:g} s")
    score = np.where(ok, c / np.maximum(overlap, 1), -np.inf)
    i = int(np.argmax(score))
    frac = 0.0
    if 0 < i < len(score) - 1 and np.isfinite(score[i - 1]) and np.isfinite(score[i + 1]):
        a, b, d = score[i - 1], score[i], score[i + 1]
        denom = a - 2 * b + d
        frac = 0.5 * (a - d) / denom if denom < 0 else 0.0
    return float(offsets[i] + frac * dt)


def umeyama(src: np.ndarray, dst: np.ndarray, with_scale: bool = False) -> Alignment:
    """The similarity (or rigid) transform taking src onto dst in least squares."""
    mu_s, mu_d = src.mean(axis=0), dst.mean(axis=0)
    a, b = src - mu_s, dst - mu_d
    U, S, Vt = np.linalg.svd(b.T @ a / len(src))
    D = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        D[2, 2] = -1
    R = U @ D @ Vt
    scale = float(np.trace(np.diag(S) @ D) / (a ** 2).sum(axis=1).mean()) if with_scale else 1.0
    return Alignment(R, mu_d - scale * R @ mu_s, scale)


def _valid_times(est: Trajectory, t_est: np.ndarray, max_gap_s: float) -> np.ndarray:
    """Times inside the estimate's span and not inside one of its gaps."""
    inside = (t_est >= est.t_s[0]) & (t_est <= est.t_s[-1])
    j = np.clip(np.searchsorted(est.t_s, t_est), 1, len(est.t_s) - 1)
    gap = est.t_s[j] - est.t_s[j - 1]
    return inside & (gap <= max_gap_s)


def _fit(ref: Trajectory, spline: CubicSpline, est: Trajectory, offset0: float,
         with_scale: bool, fit_drift: bool, max_gap_s: float):
    """Offset, drift and alignment together, robustly. Returns (TimeModel, Alignment)."""
    keep = _valid_times(est, ref.t_s + offset0, max_gap_s)
    if keep.sum() < 10:
        raise UserError("fewer than 10 poses overlap in time once the clocks are lined up")
    t_ref, p_ref = ref.t_s[keep], ref.xyz[keep]
    t_mid = float(np.median(t_ref))  # drift about the middle: offset and drift decouple
    start = umeyama(spline(t_ref + offset0), p_ref, with_scale)

    # parameters: rotation vector (3), translation (3), offset, then log scale and drift
    # (ppm) when they are fitted
    def unpack(x):
        R = Rotation.from_rotvec(x[:3]).as_matrix()
        rest = list(x[7:])
        scale = float(np.exp(rest.pop(0))) if with_scale else 1.0
        drift = rest.pop(0) * 1e-6 if fit_drift else 0.0
        return R, x[3:6], scale, x[6], drift

    def residual(x, use=slice(None)):
        R, t, scale, offset, drift = unpack(x)
        t_est = (1 + drift) * (t_ref[use] - t_mid) + t_mid + offset
        return (scale * spline(t_est) @ R.T + t - p_ref[use]).ravel()

    x = [*Rotation.from_matrix(start.R).as_rotvec(), *start.t, offset0]
    x_scale = [1e-3] * 6 + [1e-3]
    if with_scale:
        x.append(np.log(start.scale))
        x_scale.append(1e-4)
    if fit_drift:
        x.append(0.0)
        x_scale.append(1.0)
    x = np.array(x)
    # A robust first fit, then refits on the poses within 4.5 sigma of it (sigma per axis
    # from the median residual: |r| of a 3D Gaussian has median 1.54 sigma; 4.5 sigma
    # keeps 99.9 % of good poses): the estimate's blunders (a lost tracker, a reset) get
    # no say at all in the result.
    use = np.ones(len(t_ref), dtype=bool)
    for loss in ("soft_l1", "linear", "linear"):
        r = residual(x, use).reshape(-1, 3)
        sigma = 1.4826 * np.median(np.abs(r - np.median(r, axis=0))) + 1e-6
        x = least_squares(residual, x, loss=loss, f_scale=3 * sigma,
                          x_scale=np.array(x_scale), kwargs={"use": use}).x
        norm = np.linalg.norm(residual(x).reshape(-1, 3), axis=1)
        use = norm <= 4.5 * np.median(norm) / 1.54 + 1e-9
        if use.sum() < 10:
            raise UserError("the trajectories do not fit each other: check their units and "
                            "that they are of the same body")
    R, t, scale, offset, drift = unpack(x)
    # back to t_est = (1 + drift) t_ref + offset_s
    return TimeModel(offset - drift * t_mid, drift), Alignment(R, t, scale)


def _slerp(traj: Trajectory) -> Slerp:
    return Slerp(traj.t_s, Rotation.from_quat(traj.quat))


def evaluate(ref: Trajectory, est: Trajectory, with_scale: bool = False,
             fit_drift: bool = True, max_offset_s: float = 2.0, known_offset_s: float | None
             = None, rpe_delta_s: float = 1.0, fit_body_rotation: bool = False,
             max_gap_s: float | None = None) -> Evaluation:
    """Line the estimate up with the reference in time and space, then measure its errors."""
    if max_gap_s is None:
        max_gap_s = 5.0 * float(np.median(np.diff(est.t_s)))
    offset0 = (coarse_offset(ref, est, max_offset_s) if known_offset_s is None
               else float(known_offset_s))
    spline = CubicSpline(est.t_s, est.xyz)
    if known_offset_s is None or fit_drift:
        time_model, align = _fit(ref, spline, est, offset0, with_scale, fit_drift, max_gap_s)
    else:
        time_model = TimeModel(offset0)
        keep = _valid_times(est, ref.t_s + offset0, max_gap_s)
        align = umeyama(spline(ref.t_s[keep] + offset0), ref.xyz[keep], with_scale)
    t_est = time_model.to_estimate(ref.t_s)
    keep = _valid_times(est, t_est, max_gap_s)
    if keep.sum() < 10:
        raise UserError("fewer than 10 poses overlap in time")
    t_ref, t_est = ref.t_s[keep], t_est[keep]
    ref_xyz = ref.xyz[keep]
    est_xyz = align.apply(spline(t_est))
    R_ref = Rotation.from_quat(ref.quat[keep])
    R_est = Rotation.from_matrix(align.R) * _slerp(est)(t_est)
    body = np.eye(3)
    if fit_body_rotation:  # a constant rotation between the two bodies' frames
        body = (R_est.inv() * R_ref).mean().as_matrix()
    R_est_body = R_est * Rotation.from_matrix(body)
    rot_err = np.degrees((R_ref.inv() * R_est_body).magnitude())
    pos_err = np.linalg.norm(est_xyz - ref_xyz, axis=1)
    rpe_t, rpe_r = _relative_errors(t_ref, ref_xyz, R_ref, est_xyz, R_est_body, rpe_delta_s)
    return Evaluation(time_model, offset0, align, body, t_ref, ref_xyz, est_xyz, pos_err,
                      rot_err, rpe_t, rpe_r, rpe_delta_s)


def _relative_errors(t: np.ndarray, p_ref: np.ndarray, R_ref: Rotation, p_est: np.ndarray,
                     R_est: Rotation, delta_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Errors of the motion over delta_s: (inv(Ref_i) Ref_j)^-1 (inv(Est_i) Est_j) for the
    pose j nearest delta_s after each pose i."""
    j = np.searchsorted(t, t + delta_s)
    ok = j < len(t)
    i, j = np.flatnonzero(ok), j[ok]
    if not len(i):
        return np.zeros(0), np.zeros(0)
    close = np.abs(t[j] - t[i] - delta_s) <= 0.1 * delta_s + 1e-9
    i, j = i[close], j[close]
    d_ref = R_ref[i].inv().apply(p_ref[j] - p_ref[i])
    d_est = R_est[i].inv().apply(p_est[j] - p_est[i])
    rel_ref = R_ref[i].inv() * R_ref[j]
    rel_est = R_est[i].inv() * R_est[j]
    err_t = np.linalg.norm(rel_ref.inv().apply(d_est - d_ref), axis=1)
    err_r = np.degrees((rel_ref.inv() * rel_est).magnitude())
    return err_t, err_r


def _stats(values: np.ndarray, unit: float, gross: float | None = None) -> dict:
    v = values * unit
    if not len(v):
        return {"n": 0}
    out = {"n": int(len(v)), "rms": float(np.sqrt(np.mean(v ** 2))),
           "mean": float(v.mean()), "median": float(np.median(v)), "max": float(v.max())}
    if gross is not None:
        out["gross"] = int(np.sum(v > gross))
        out["gross_limit"] = gross
    return out


def figures(ev: Evaluation, gross_mm: float = 50.0, gross_deg: float = 5.0) -> dict:
    """The evaluation's numbers for --json and the report: every pose counted, gross errors
    counted beside the RMS."""
    return {
        "poses_compared": int(len(ev.t_s)),
        "time": {"offset_s": ev.time.offset_s, "drift_ppm": ev.time.drift * 1e6,
                 "coarse_offset_s": ev.coarse_offset_s},
        "alignment": {"rotation_deg": float(np.degrees(
            Rotation.from_matrix(ev.alignment.R).magnitude())),
            "rotvec": Rotation.from_matrix(ev.alignment.R).as_rotvec().tolist(),
            "translation_m": ev.alignment.t.tolist(), "scale": ev.alignment.scale},
        "body_rotation_deg": float(np.degrees(Rotation.from_matrix(ev.body_rotation)
                                              .magnitude())),
        "ate_position_mm": _stats(ev.position_error_m, 1000.0, gross_mm),
        "ate_rotation_deg": _stats(ev.rotation_error_deg, 1.0, gross_deg),
        "rpe": {"delta_s": ev.rpe_delta_s,
                "translation_mm": _stats(ev.rpe_translation_m, 1000.0),
                "rotation_deg": _stats(ev.rpe_rotation_deg, 1.0)},
    }
