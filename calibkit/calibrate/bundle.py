"""The GTSAM factor graph that refines every camera at once: poses, optionally intrinsics,
3D points, wand lengths, and points known in the world or on known planes.

It reads top to bottom as the maths does: noise models, factors, initial values, the
optimiser, the result; then outlier rejection and a re-solve, and marginal covariances
with the gauge fixed. The hot part (tens of thousands of projections) uses GTSAM's built-in
C++ factors only: a Python CustomFactor per observation makes a solve ~60 times slower.

Intrinsics, when refined, are one Cal3DS2 per camera shared by all its observations, with a
diagonal prior at the starting values (calibkit.calibrate.intrinsic_prior gives the sigmas from the
intrinsic step's uncertainty). The intrinsic step's target views (calibkit.calibrate.bundle_target:
a monitor's dots, each view a pose variable, the dots at their known places, seen through
the camera's shared Cal3DS2) can join the graph, so the target and the wand refine the
intrinsics together, each weighted by its own noise.

Conventions: GTSAM's camera Pose3 is camera-to-world (the inverse of ours). Cal3DS2 has
k1, k2, p1, p2 but no k3; a camera whose k3 is not zero gets its measurements corrected
once (undistorted with the full model, distorted again without k3), which is exact while
intrinsics are held and leaves a second-order error when they are refined; k3 itself is
never refined and is written back unchanged.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import gtsam
import numpy as np

from calibkit.calibrate import bundle_target
from calibkit.calibrate.bundle_target import TargetData
from calibkit.core.camera import Camera, Rig
from calibkit.core.geometry import RigArrays

X = gtsam.symbol_shorthand.X  # camera poses
P = gtsam.symbol_shorthand.P  # 3D points
K = gtsam.symbol_shorthand.K  # intrinsics (Cal3DS2)
@dataclass(eq=False)
class BundleData:
    """What the graph is built from. Observations are (point, camera, pixel) rows; points
    may be tied by known distances (the wand), fixed in the world (surveyed points) or held
    on planes n.x = d (the projector's floor and table dots)."""

    rig: Rig  # initial cameras: intrinsics and poses
    obs_point: np.ndarray  # (M,) int
    obs_camera: np.ndarray  # (M,) int
    obs_uv: np.ndarray  # (M, 2) distorted pixels
    xyz: np.ndarray  # (P, 3) initial points, metres
    edge: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), dtype=np.int64))
    edge_length_m: np.ndarray = field(default_factory=lambda: np.zeros(0))
    known_point: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    known_xyz: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    plane_point: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    plane_normal: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    plane_offset_m: np.ndarray = field(default_factory=lambda: np.zeros(0))
    target: TargetData | None = None  # the intrinsic step's views, used when refining

    def __post_init__(self) -> None:
        self.obs_point = np.asarray(self.obs_point, dtype=np.int64)
        self.obs_camera = np.asarray(self.obs_camera, dtype=np.int64)
        self.obs_uv = np.asarray(self.obs_uv, dtype=np.float64).reshape(-1, 2)
        self.xyz = np.asarray(self.xyz, dtype=np.float64).reshape(-1, 3)
        self.edge = np.asarray(self.edge, dtype=np.int64).reshape(-1, 2)
        self.edge_length_m = np.asarray(self.edge_length_m, dtype=np.float64).reshape(-1)
        self.known_point = np.asarray(self.known_point, dtype=np.int64).reshape(-1)
        self.known_xyz = np.asarray(self.known_xyz, dtype=np.float64).reshape(-1, 3)
        self.plane_point = np.asarray(self.plane_point, dtype=np.int64).reshape(-1)
        self.plane_normal = np.asarray(self.plane_normal, dtype=np.float64).reshape(-1, 3)
        self.plane_offset_m = np.asarray(self.plane_offset_m, dtype=np.float64).reshape(-1)


@dataclass(frozen=True)
class BundleOptions:
    noise_px: float = 0.5  # first guess of the image noise; re-estimated after round one
    huber_k: float = 1.345  # Huber threshold in standard deviations
    length_sigma_m: float = 1e-4  # how well the wand's marker distances are known
    known_sigma_m: float = 1e-3  # surveyed points
    plane_sigma_m: float = 1e-3  # points on a known plane, along its normal
    refine_intrinsics: bool = False
    # priors on the intrinsics when refined: per camera, Cal3DS2's 9 sigmas (fx fy skew cx cy
    # k1 k2 p1 p2; calibkit.calibrate.intrinsic_prior.prior_sigmas), else these for every camera
    intrinsic_sigma: tuple[tuple[float, ...], ...] | None = None
    focal_sigma_px: float = 5.0
    centre_sigma_px: float = 5.0
    radial_sigma: float = 0.02
    tangential_sigma: float = 0.002
    reference_camera: int = 0  # gauge: held where it starts unless known points fix the frame
    max_iterations: int = 100
    outlier_sigmas: float = 4.3  # a residual beyond this many robust sigmas is an outlier
    rounds: int = 2  # solve, drop outliers, solve again
    # rounds solved with the Huber loss; the later ones are plain least squares on the
    # inliers: the maximum-likelihood fit for Gaussian noise once the outliers are out, and
    # Gauss-Newton then converges in two or three iterations where reweighting Huber's
    # residuals crawls (each of ~10 iterations taking half the previous one's decrease)
    robust_rounds: int = 1
    # the noise and the outlier test on residuals standardised by their point's redundancy
    # (see standardised): the wand solve's; the projector's dots (points on planes, held by
    # priors the count does not know) keep the plain residuals
    standardise: bool = False


@dataclass(eq=False)
class BundleResult:
    rig: Rig
    xyz: np.ndarray  # (P, 3) refined points (NaN for points left out)
    residual_px: np.ndarray  # (M, 2) observed minus projected, every row
    inlier: np.ndarray  # (M,) bool: used in the final solve
    noise_px: float  # robust estimate of the image noise
    iterations: int
    initial_error: float
    final_error: float
    time_s: float  # wall clock
    data: BundleData
    options: BundleOptions
    cpu_s: float = float("nan")  # this process's CPU time (one core: the time on a quiet machine)
    values: object = None  # gtsam.Values of the final solve
    graph: object = None  # gtsam.NonlinearFactorGraph of the final solve
    # the target views in the final solve (their solved poses), observed minus projected
    # pixels, the rows used and each camera's robust noise (NaN without views)
    target: TargetData | None = None
    target_residual_px: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    target_inlier: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))
    target_noise_px: np.ndarray = field(default_factory=lambda: np.zeros(0))


# ---- the camera model in GTSAM's terms ----------------------------------------------------------

def _cal(cam: Camera) -> gtsam.Cal3DS2:
    k1, k2, p1, p2, _k3 = cam.dist
    return gtsam.Cal3DS2(cam.fx, cam.fy, cam.skew, cam.cx, cam.cy, k1, k2, p1, p2)


def _pose(cam: Camera) -> gtsam.Pose3:
    """Our world-to-camera (R, t) as GTSAM's camera-to-world pose."""
    return gtsam.Pose3(gtsam.Rot3(cam.R.T), cam.centre)


def _camera(cam: Camera, pose: gtsam.Pose3, cal: gtsam.Cal3DS2 | None) -> Camera:
    R = pose.rotation().matrix().T
    t = -R @ pose.translation()
    if cal is None:
        return cam.replace(R=R, t=t)
    v = cal.vector()  # fx fy s u0 v0 k1 k2 p1 p2
    dist = np.array([v[5], v[6], v[7], v[8], cam.dist[4]])
    return cam.replace(R=R, t=t, fx=v[0], fy=v[1], skew=v[2], cx=v[3], cy=v[4], dist=dist)


def remove_k3(rig: Rig, camera: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Pixels as the same camera without k3 would have seen them: undistorted with the full
    model, distorted again with k1, k2, p1, p2 only."""
    arrays = RigArrays.from_rig(rig)
    k1, k2, p1, p2, k3 = arrays.dist[camera].T
    if not np.any(k3):
        return uv
    n = arrays.undistort(camera, uv)
    x, y = n[:, 0], n[:, 1]
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * k2)
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    out = np.stack([arrays.fx[camera] * xd + arrays.skew[camera] * yd + arrays.cx[camera],
                    arrays.fy[camera] * yd + arrays.cy[camera]], axis=1)
    return np.where((k3 != 0)[:, None], out, uv)


def residuals(rig: Rig, data: BundleData, xyz: np.ndarray) -> np.ndarray:
    """Observed minus projected pixels (M, 2) for every observation; NaN where a point is
    missing or behind its camera."""
    proj, z = RigArrays.from_rig(rig).project(data.obs_camera, xyz[data.obs_point])
    r = data.obs_uv - proj
    r[~(z > 0)] = np.nan
    return r


def per_camera_sigma(r: np.ndarray, camera: np.ndarray, n_cams: int) -> np.ndarray:
    """robust_sigma of each camera's rows (NaN for a camera without any)."""
    return np.array([robust_sigma(r[camera == c]) for c in range(n_cams)])


def standardised(r: np.ndarray, point: np.ndarray, use: np.ndarray) -> np.ndarray:
    """Residuals divided by sqrt(1 - 3 / (2 n)), n the cameras that see their point in the
    rows `use`: a point fitted to 2n pixel coordinates absorbs 3 of them, so its residuals
    are that much smaller than the noise (half of it for a point two cameras see). Unscaled,
    a capture of mostly two-view points (a few cameras, a hand-digitised wand) gives a noise
    estimate half the true one, and the outlier test then drops the good rows of points
    seen three times and more: 5-8 % of a 3-camera, 50-frame capture at 0.7 px."""
    n = np.bincount(point[use], minlength=int(point.max()) + 1 if len(point) else 0)[point]
    scale = np.sqrt(np.clip(1.0 - 1.5 / np.maximum(n, 1), 0.1, 1.0))
    return r / scale[:, None]


def robust_sigma(r: np.ndarray) -> float:
    """Per-axis noise from the median absolute residual (1.4826 MAD), outliers ignored."""
    a = np.abs(r[np.isfinite(r)])
    return float(1.4826 * np.median(a)) if len(a) else float("nan")


# ---- the graph ----------------------------------------------------------------------------------

def _intrinsic_sigmas(options: BundleOptions, n_cams: int) -> np.ndarray:
    if options.intrinsic_sigma is not None:
        sigma = np.asarray(options.intrinsic_sigma, dtype=np.float64).reshape(-1, 9)
        if len(sigma) != n_cams:
            raise ValueError(f"intrinsic_sigma has {len(sigma)} rows for {n_cams} cameras")
        return sigma
    return np.tile([options.focal_sigma_px, options.focal_sigma_px, 1e-6,
                    options.centre_sigma_px, options.centre_sigma_px, options.radial_sigma,
                    options.radial_sigma, options.tangential_sigma, options.tangential_sigma],
                   (n_cams, 1))


def build_graph(data: BundleData, uv: np.ndarray, use: np.ndarray, noise_px: float,
                options: BundleOptions, xyz: np.ndarray, rig: Rig,
                tight_gauge: bool = False, prior_rig: Rig | None = None,
                target: TargetData | None = None, target_use: np.ndarray | None = None,
                target_noise_px: np.ndarray | None = None, robust: bool = True
                ) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values, np.ndarray]:
    """Noise models, factors and initial values. Returns the graph, the values and the
    points that take part (seen by two or more cameras in the rows `use`). `rig` holds the
    starting values; the intrinsics' priors sit at `prior_rig`'s (the intrinsic step's;
    default `rig`), so a second round starts from the first's result without moving them.
    `target` (its pixels k3-corrected, its views' poses the starting values) joins the
    graph when the intrinsics are refined: rows `target_use`, each camera's pixels with
    its own noise `target_noise_px`. `robust`: the Huber loss on the wand's pixels, else
    plain least squares."""
    n_cams = len(rig)
    # -- which points take part
    n_seen = np.bincount(data.obs_point[use], minlength=len(xyz))
    known = np.zeros(len(xyz), dtype=bool)
    known[data.known_point] = True
    active = ((n_seen >= 2) | (known & (n_seen >= 1))) & np.isfinite(xyz).all(axis=1)
    rows = np.flatnonzero(use & active[data.obs_point])

    # -- noise models
    pixel = gtsam.noiseModel.Isotropic.Sigma(2, noise_px)
    if robust:
        pixel = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(
            options.huber_k), pixel)
    length = gtsam.noiseModel.Isotropic.Sigma(1, options.length_sigma_m)
    surveyed = gtsam.noiseModel.Isotropic.Sigma(3, options.known_sigma_m)
    # a tight gauge for marginals; a weak one when plane points fix part of the frame
    planes = bool(np.any(active[data.plane_point])) if len(data.plane_point) else False
    gauge_sigma = 1e-6 if tight_gauge else (10.0 if planes else 1e-3)
    gauge = gtsam.noiseModel.Isotropic.Sigma(6, gauge_sigma)
    intrinsic = [gtsam.noiseModel.Diagonal.Sigmas(np.asarray(s, dtype=np.float64))
                 for s in _intrinsic_sigmas(options, n_cams)]

    graph = gtsam.NonlinearFactorGraph()
    cals = [_cal(c) for c in rig]
    prior_cals = [_cal(c) for c in (prior_rig or rig)]
    # -- projection factors: the hot part, built-in C++ factors only
    pts, cams, meas = data.obs_point[rows], data.obs_camera[rows], uv[rows]
    if options.refine_intrinsics:
        for p, c, m in zip(pts.tolist(), cams.tolist(), meas, strict=True):
            graph.add(gtsam.GeneralSFMFactor2Cal3DS2(m, pixel, X(c), P(p), K(c)))
        for c in range(n_cams):
            graph.add(gtsam.PriorFactorCal3DS2(K(c), prior_cals[c], intrinsic[c]))
    else:
        for p, c, m in zip(pts.tolist(), cams.tolist(), meas, strict=True):
            graph.add(gtsam.GenericProjectionFactorCal3DS2(m, pixel, X(c), P(p), cals[c]))
    # -- the wand: distances between its markers (RangeFactor3 is point-to-point)
    edge_ok = active[data.edge[:, 0]] & active[data.edge[:, 1]] if len(data.edge) else \
        np.zeros(0, dtype=bool)
    for (i, j), d in zip(data.edge[edge_ok].tolist(), data.edge_length_m[edge_ok].tolist(),
                         strict=True):
        graph.add(gtsam.RangeFactor3(P(i), P(j), d, length))
    # -- points known in the world, and points on known planes
    for i, x in zip(data.known_point.tolist(), data.known_xyz, strict=True):
        if active[i]:
            graph.add(gtsam.PriorFactorPoint3(P(i), x, surveyed))
    for i, n, d in zip(data.plane_point.tolist(), data.plane_normal, data.plane_offset_m,
                       strict=True):
        if active[i]:
            n = n / np.linalg.norm(n)
            info = np.outer(n, n) / options.plane_sigma_m**2 + np.eye(3) * 1e-9
            on_plane = xyz[i] - (n @ xyz[i] - d) * n
            graph.add(gtsam.PriorFactorPoint3(P(i), on_plane,
                                              gtsam.noiseModel.Gaussian.Information(info)))
    # -- the gauge: hold the reference camera unless surveyed points fix the frame
    n_known = int(np.sum(active[data.known_point]))
    ref = options.reference_camera
    if n_known < 3 or tight_gauge:
        graph.add(gtsam.PriorFactorPose3(X(ref), _pose(rig[ref]), gauge))
    if len(data.edge) == 0 and n_known < 3:  # no wand length: hold the scale as it starts
        far = int(np.argmax(np.linalg.norm(rig.centres() - rig[ref].centre, axis=1)))
        dist = float(np.linalg.norm(rig[far].centre - rig[ref].centre))
        graph.add(gtsam.RangeFactorPose3(X(ref), X(far), dist,
                                         gtsam.noiseModel.Isotropic.Sigma(1, 1e-6)))

    # -- initial values
    values = gtsam.Values()
    for c, cam in enumerate(rig):
        values.insert(X(c), _pose(cam))
        if options.refine_intrinsics:
            values.insert(K(c), cals[c])
    for i in np.flatnonzero(active).tolist():
        values.insert(P(i), xyz[i])
    if target is not None and options.refine_intrinsics and len(target):
        bundle_target.add_factors(graph, values, target, target_use, target_noise_px, K)
    return graph, values, active


def _optimise(graph, values, options: BundleOptions, progress=None):
    """Levenberg-Marquardt, one iteration at a time so that long solves can show progress."""
    params = gtsam.LevenbergMarquardtParams()
    params.setOrderingType("METIS")  # 10-30 % less per iteration than COLAMD here
    params.setMaxIterations(options.max_iterations)
    params.setRelativeErrorTol(1e-7)
    params.setAbsoluteErrorTol(1e-9)
    optimiser = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
    initial = error = optimiser.error()
    for _ in range(options.max_iterations):
        optimiser.iterate()
        new = optimiser.error()
        if progress is not None:
            progress(optimiser.iterations(), new)
        if gtsam.checkConvergence(1e-7, 1e-9, 0.0, error, new) or \
                optimiser.lambda_() > params.getlambdaUpperBound():
            error = new
            break
        error = new
    return optimiser.values(), optimiser.iterations(), initial, error


def _read(result: gtsam.Values, rig: Rig, active: np.ndarray, n_points: int,
          options: BundleOptions) -> tuple[Rig, np.ndarray]:
    cams = []
    for c, cam in enumerate(rig):
        cal = result.atCal3DS2(K(c)) if options.refine_intrinsics else None
        cams.append(_camera(cam, result.atPose3(X(c)), cal))
    xyz = np.full((n_points, 3), np.nan)
    idx = np.flatnonzero(active)
    if len(idx):
        xyz[idx] = np.array([result.atPoint3(P(i)) for i in idx.tolist()])
    return Rig(tuple(cams), dict(rig.quality), dict(rig.meta)), xyz


def solve(data: BundleData, options: BundleOptions = BundleOptions(),
          progress=None) -> BundleResult:
    """Levenberg-Marquardt on the whole graph; then drop observations beyond
    `outlier_sigmas` robust sigmas and solve again with the noise re-estimated (the wand's
    over all its rows, the target views' per camera). progress(text), if given, hears of
    every iteration."""
    start, start_cpu = time.perf_counter(), time.process_time()
    uv = remove_k3(data.rig, data.obs_camera, data.obs_uv)
    k3_free = Rig(tuple(c.replace(dist=c.dist * [1, 1, 1, 1, 0]) for c in data.rig),
                  dict(data.rig.quality), dict(data.rig.meta))
    target = data.target if options.refine_intrinsics and data.target is not None and \
        len(data.target) else None
    if target is not None:
        target = target.replace(obs_uv=remove_k3(data.rig, target.obs_camera, target.obs_uv))
    corrected = BundleData(**{**data.__dict__, "rig": k3_free, "obs_uv": uv,
                              "target": target})
    rig, xyz = k3_free, data.xyz.copy()
    use = np.ones(len(uv), dtype=bool)
    noise = options.noise_px
    t_use = t_noise = t_res = None
    if target is not None:
        t_res = bundle_target.residuals(rig, target)
        t_noise = per_camera_sigma(t_res, target.obs_camera, len(rig))
        t_use = np.isfinite(t_res[:, 0])
    iterations, first_error = 0, None
    for round_ in range(max(1, options.rounds)):
        graph, values, active = build_graph(corrected, uv, use, noise, options, xyz, rig,
                                            prior_rig=k3_free, target=target,
                                            target_use=t_use, target_noise_px=t_noise,
                                            robust=round_ < options.robust_rounds)
        report = None if progress is None else (
            lambda i, e, r=round_: progress(f"round {r + 1}, iteration {i}, error {e:.6g}"))
        result, its, e0, e1 = _optimise(graph, values, options, report)
        iterations += its
        first_error = e0 if first_error is None else first_error
        rig, xyz = _read(result, rig, active, len(xyz), options)
        r = residuals(rig, corrected, xyz)
        # residuals standardised by their point's redundancy before the noise and the
        # outlier test see them (see standardised)
        r_std = standardised(r, data.obs_point, use & active[data.obs_point]) \
            if options.standardise else r
        noise = robust_sigma(r_std[use])
        if target is not None:
            target = bundle_target.read_views(result, target)
            t_res = bundle_target.residuals(rig, target)
            t_noise = per_camera_sigma(np.where(t_use[:, None], t_res, np.nan),
                                       target.obs_camera, len(rig))
        if round_ + 1 < options.rounds:
            norm = np.linalg.norm(r_std, axis=1)
            use = np.isfinite(norm) & (norm <= options.outlier_sigmas * noise)
            if target is not None:
                t_norm = np.linalg.norm(t_res, axis=1)
                t_use = np.isfinite(t_norm) & (
                    t_norm <= options.outlier_sigmas * t_noise[target.obs_camera])
    r = residuals(rig, corrected, xyz)
    final = Rig(tuple(c.replace(dist=np.r_[c.dist[:4], d.dist[4]])
                      for c, d in zip(rig, data.rig, strict=True)), dict(data.rig.quality),
                dict(data.rig.meta))
    out = BundleResult(final, xyz, r, use & np.isfinite(r[:, 0]), noise, iterations,
                       float(first_error), float(e1), time.perf_counter() - start, corrected,
                       options, time.process_time() - start_cpu, result, graph)
    if target is not None:
        out.target, out.target_residual_px = target, t_res
        out.target_inlier, out.target_noise_px = t_use & np.isfinite(t_res[:, 0]), t_noise
    return out


# ---- uncertainty ---------------------------------------------------------------------

def camera_covariances(result: BundleResult) -> dict:
    """Each camera's position and orientation standard deviations from the marginal
    covariances, with the gauge fixed tightly at the reference camera (so its own are ~0
    and the others' are relative to it). Units: metres and radians, world axes."""
    data, options = result.data, result.options
    k3_free = Rig(tuple(c.replace(dist=c.dist * [1, 1, 1, 1, 0]) for c in result.rig))
    graph, values, _ = build_graph(data, data.obs_uv, result.inlier, result.noise_px, options,
                                   result.xyz, k3_free, tight_gauge=True, prior_rig=data.rig,
                                   target=result.target, target_use=result.target_inlier,
                                   target_noise_px=result.target_noise_px,
                                   robust=options.rounds <= options.robust_rounds)
    marginals = gtsam.Marginals(graph, values)
    pos, rot = [], []
    for c, cam in enumerate(result.rig):
        cov = marginals.marginalCovariance(X(c))  # tangent [rotation, translation], body
        Rwc = cam.R.T
        pos.append(np.sqrt(np.clip(np.diag(Rwc @ cov[3:, 3:] @ Rwc.T), 0, None)))
        rot.append(np.sqrt(np.clip(np.diag(Rwc @ cov[:3, :3] @ Rwc.T), 0, None)))
    pos_a, rot_a = np.array(pos), np.array(rot)
    out = {"reference_camera": result.rig[options.reference_camera].name,
           "position_std_m": pos_a, "orientation_std_rad": rot_a,
           "position_std_total_m": np.linalg.norm(pos_a, axis=1),
           "orientation_std_total_rad": np.linalg.norm(rot_a, axis=1)}
    if options.refine_intrinsics:  # how well the solve knows each camera's Cal3DS2 values
        out["intrinsic_std"] = np.array([np.sqrt(np.clip(np.diag(
            marginals.marginalCovariance(K(c))), 0, None)) for c in range(len(result.rig))])
    return out
