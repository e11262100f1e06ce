"""Triangulation of markers from any number of cameras, and rigid/similarity fits.

Everything is batched over observations: a rig's parameters are stacked into arrays once
(`RigArrays`), so undistorting, projecting and differentiating thousands of observations
from different cameras is a handful of numpy operations, not a loop per point or camera.
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass

import numpy as np

from calibkit.core.camera import Rig


@dataclass(frozen=True, eq=False)
class RigArrays:
    """A rig's cameras as stacked arrays, indexed by camera number."""

    R: np.ndarray  # (C, 3, 3) world-to-camera
    t: np.ndarray  # (C, 3)
    centre: np.ndarray  # (C, 3)
    fx: np.ndarray  # (C,)
    fy: np.ndarray
    cx: np.ndarray
    cy: np.ndarray
    skew: np.ndarray
    dist: np.ndarray  # (C, 5) k1 k2 p1 p2 k3

    @classmethod
    def from_rig(cls, rig: Rig) -> RigArrays:
        cached = _ARRAYS.get(rig)
        if cached is None:
            cams = list(rig)
            cached = cls(
                np.array([c.R for c in cams]).reshape(-1, 3, 3),
                np.array([c.t for c in cams]).reshape(-1, 3),
                np.array([c.centre for c in cams]).reshape(-1, 3),
                np.array([c.fx for c in cams]), np.array([c.fy for c in cams]),
                np.array([c.cx for c in cams]), np.array([c.cy for c in cams]),
                np.array([c.skew for c in cams]),
                np.array([c.dist for c in cams]).reshape(-1, 5))
            _ARRAYS[rig] = cached
        return cached

    def undistort(self, camera: np.ndarray, uv: np.ndarray, iterations: int = 20) -> np.ndarray:
        """Pixels (M, 2) seen by cameras `camera` (M,) -> normalised coordinates (M, 2)."""
        yd = (uv[:, 1] - self.cy[camera]) / self.fy[camera]
        xd = (uv[:, 0] - self.cx[camera] - self.skew[camera] * yd) / self.fx[camera]
        k1, k2, p1, p2, k3 = self.dist[camera].T
        x, y = xd.copy(), yd.copy()
        if not np.any(self.dist[camera]):
            return np.stack([x, y], axis=1)
        for _ in range(iterations):
            r2 = x * x + y * y
            radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
            dradial = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)
            ex = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x) - xd
            ey = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y - yd
            j11 = radial + 2.0 * x * x * dradial + 2.0 * p1 * y + 6.0 * p2 * x
            j12 = 2.0 * x * y * dradial + 2.0 * p1 * x + 2.0 * p2 * y
            j22 = radial + 2.0 * y * y * dradial + 6.0 * p1 * y + 2.0 * p2 * x
            det = j11 * j22 - j12 * j12
            det = np.where(np.abs(det) < 1e-12, 1e-12, det)
            dx = (j22 * ex - j12 * ey) / det
            dy = (j11 * ey - j12 * ex) / det
            x -= dx
            y -= dy
            if np.max(np.abs(dx), initial=0.0) < 1e-14 and np.max(np.abs(dy), initial=0.0) < 1e-14:
                break
        return np.stack([x, y], axis=1)

    def rays(self, camera: np.ndarray, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World ray origins and unit directions (M, 3) of pixels seen by `camera`."""
        n = self.undistort(camera, uv)
        d_cam = np.concatenate([n, np.ones((len(n), 1))], axis=1)
        d = np.einsum("mji,mj->mi", self.R[camera], d_cam)  # R^T d_cam
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        return self.centre[camera], d

    def project(self, camera: np.ndarray, xyz: np.ndarray, jacobian: bool = False):
        """World points (M, 3), each seen by camera[m] -> pixels (M, 2), depth (M,) and, if
        asked, d pixels / d xyz (M, 2, 3)."""
        Rm = self.R[camera]
        pc = np.einsum("mij,mj->mi", Rm, xyz) + self.t[camera]
        z = pc[:, 2]
        zs = np.where(np.abs(z) < 1e-12, 1e-12, z)
        x, y = pc[:, 0] / zs, pc[:, 1] / zs
        k1, k2, p1, p2, k3 = self.dist[camera].T
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
        yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
        fx, fy, skew = self.fx[camera], self.fy[camera], self.skew[camera]
        uv = np.stack([fx * xd + skew * yd + self.cx[camera], fy * yd + self.cy[camera]], axis=1)
        if not jacobian:
            return uv, z
        dradial = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)
        j11 = radial + 2.0 * x * x * dradial + 2.0 * p1 * y + 6.0 * p2 * x
        j12 = 2.0 * x * y * dradial + 2.0 * p1 * x + 2.0 * p2 * y
        j22 = radial + 2.0 * y * y * dradial + 6.0 * p1 * y + 2.0 * p2 * x
        # d(u, v)/d(x, y): K's upper 2x2 times the distortion Jacobian
        a11 = fx * j11 + skew * j12
        a12 = fx * j12 + skew * j22
        a21 = fy * j12
        a22 = fy * j22
        # d(x, y)/d(pc): [[1/z, 0, -x/z], [0, 1/z, -y/z]]
        inv_z = 1.0 / zs
        J = np.empty((len(z), 2, 3))
        J[:, 0, 0] = a11 * inv_z
        J[:, 0, 1] = a12 * inv_z
        J[:, 0, 2] = -(a11 * x + a12 * y) * inv_z
        J[:, 1, 0] = a21 * inv_z
        J[:, 1, 1] = a22 * inv_z
        J[:, 1, 2] = -(a21 * x + a22 * y) * inv_z
        return uv, z, J @ Rm


_ARRAYS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


@dataclass(eq=False)
class Triangulation:
    """3D points and their quality figures; NaN where a point could not be triangulated."""

    xyz: np.ndarray  # (P, 3) metres
    reproj_px: np.ndarray  # (P,) RMS reprojection error over the point's observations
    ray_dist_m: np.ndarray  # (P,) mean distance between pairs of the point's rays
    n_cameras: np.ndarray  # (P,) observations used

    @property
    def ok(self) -> np.ndarray:
        return np.isfinite(self.xyz[:, 0])


def _solve3(A: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Batched 3x3 solves by the adjugate (several times faster than np.linalg.solve on
    tiny systems); singular or non-finite systems give NaN rather than an exception."""
    a, b_, c = A[:, 0, 0], A[:, 0, 1], A[:, 0, 2]
    d, e, f = A[:, 1, 0], A[:, 1, 1], A[:, 1, 2]
    g, h, i = A[:, 2, 0], A[:, 2, 1], A[:, 2, 2]
    co0, co1, co2 = e * i - f * h, f * g - d * i, d * h - e * g
    with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
        det = a * co0 + b_ * co1 + c * co2
        scale = np.abs(A).max(axis=(1, 2))
        good = np.abs(det) > 1e-18 * np.maximum(1.0, scale) ** 3
        inv_det = np.where(good, 1.0 / np.where(good, det, 1.0), np.nan)
        x, y, z = b[:, 0], b[:, 1], b[:, 2]
        out = np.stack([
            co0 * x + (c * h - b_ * i) * y + (b_ * f - c * e) * z,
            co1 * x + (a * i - c * g) * y + (c * d - a * f) * z,
            co2 * x + (b_ * g - a * h) * y + (a * e - b_ * d) * z,
        ], axis=1) * inv_det[:, None]
    return out


def group_sum(index: np.ndarray, values: np.ndarray, n: int) -> np.ndarray:
    """Sum rows of `values` (M, ...) into n groups by `index` (M,): bincount per column,
    several times faster than np.add.at."""
    flat = values.reshape(len(values), -1)
    out = np.empty((n, flat.shape[1]))
    for j in range(flat.shape[1]):
        out[:, j] = np.bincount(index, weights=flat[:, j], minlength=n)
    return out.reshape((n,) + values.shape[1:])


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.stack([a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1],
                     a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2],
                     a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]], axis=1)


def closest_point_to_rays(point: np.ndarray, origins: np.ndarray, dirs: np.ndarray,
                          n_points: int) -> np.ndarray:
    """Least-squares point nearest to each group of rays (sum of squared distances)."""
    P = np.eye(3)[None] - dirs[:, :, None] * dirs[:, None, :]  # (M, 3, 3) projectors
    A = group_sum(point, P, n_points)
    b = group_sum(point, np.einsum("mij,mj->mi", P, origins), n_points)
    return _solve3(A, b)


def mean_ray_distance(point: np.ndarray, origins: np.ndarray, dirs: np.ndarray,
                      n_points: int) -> np.ndarray:
    """Mean distance between every pair of rays of each point (the seed thesis's figure)."""
    order = np.argsort(point, kind="stable")
    p, o, d = point[order], origins[order], dirs[order]
    total = np.zeros(n_points)
    count = np.zeros(n_points)
    counts = np.bincount(point, minlength=n_points)
    for shift in range(1, int(counts.max(initial=0))):
        same = p[:-shift] == p[shift:]
        if not np.any(same):
            break
        i = np.flatnonzero(same)
        j = i + shift
        cross = _cross(d[i], d[j])
        norm = np.linalg.norm(cross, axis=1)
        w = o[j] - o[i]
        skew_dist = np.abs(np.sum(w * cross, axis=1)) / np.maximum(norm, 1e-15)
        # nearly parallel rays: distance of one origin from the other line
        along = w - np.sum(w * d[i], axis=1, keepdims=True) * d[i]
        dist = np.where(norm > 1e-9, skew_dist, np.linalg.norm(along, axis=1))
        total += np.bincount(p[i], weights=dist, minlength=n_points)
        count += np.bincount(p[i], minlength=n_points)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(count > 0, total / count, np.nan)


def triangulate(rig: Rig, point: np.ndarray, camera: np.ndarray, uv: np.ndarray,
                iterations: int = 3, n_points: int | None = None,
                ray_distance: bool = True,
                rays: tuple[np.ndarray, np.ndarray] | None = None,
                start: np.ndarray | None = None, compiled: bool = True) -> Triangulation:
    """Triangulate P points from M observations (point index, camera index, distorted pixels).

    Linear least squares on the undistorted rays gives the start; `iterations` Gauss-Newton
    steps then minimise the reprojection error in pixels, which is what the noise lives in
    (the ray solution weights far cameras too little). Points seen by fewer than two
    cameras, or that end up behind one of their cameras, are NaN. `ray_distance=False`
    skips the pairwise ray figure (NaN) where only positions are needed, as in tracking.
    `rays` (origins, directions) may be given when the caller has already computed them,
    and `start` (P, 3) positions to refine instead of the linear solution.
    `compiled=False` runs the numpy implementation the compiled kernel is tested against.
    """
    arrays = RigArrays.from_rig(rig)
    point = np.asarray(point, dtype=np.int64).reshape(-1)
    camera = np.asarray(camera, dtype=np.int64).reshape(-1)
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    n = int(point.max(initial=-1)) + 1 if n_points is None else int(n_points)
    n_cams = np.bincount(point, minlength=n).astype(np.int64)
    if len(point) == 0:
        empty = np.zeros(n)
        return Triangulation(np.full((n, 3), np.nan), empty + np.nan, empty + np.nan, n_cams)
    origins, dirs = arrays.rays(camera, uv) if rays is None else rays
    if compiled:
        return _triangulate_compiled(arrays, point, camera, uv, origins, dirs, iterations, n,
                                     n_cams, ray_distance, start)
    if start is None:
        xyz = closest_point_to_rays(point, origins, dirs, n)
    else:
        xyz = np.array(start, dtype=np.float64).reshape(n, 3)
        missing = ~np.isfinite(xyz).all(axis=1)
        if np.any(missing):
            xyz[missing] = closest_point_to_rays(point, origins, dirs, n)[missing]
    xyz[n_cams < 2] = np.nan
    for _ in range(iterations):
        proj, z, J = arrays.project(camera, xyz[point], jacobian=True)
        r = proj - uv
        JtJ = J[:, 0, :, None] * J[:, 0, None, :] + J[:, 1, :, None] * J[:, 1, None, :]
        H = group_sum(point, JtJ, n)
        g = group_sum(point, np.einsum("mki,mk->mi", J, r), n)
        step = _solve3(H, g)
        finite = np.isfinite(step[:, 0])
        xyz[finite] -= step[finite]
    proj, z = arrays.project(camera, xyz[point])
    sq = np.sum((proj - uv) ** 2, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        reproj = np.sqrt(np.bincount(point, weights=sq, minlength=n) / n_cams)
    behind = np.bincount(point, weights=~(z > 0), minlength=n) > 0
    bad = behind | (n_cams < 2) | ~np.isfinite(xyz[:, 0])
    xyz[bad] = np.nan
    reproj[bad] = np.nan
    ray = mean_ray_distance(point, origins, dirs, n) if ray_distance else np.full(n, np.nan)
    ray[bad] = np.nan
    return Triangulation(xyz, reproj, ray, n_cams)


def _triangulate_compiled(arrays: RigArrays, point, camera, uv, origins, dirs, iterations,
                          n, n_cams, ray_distance, start) -> Triangulation:
    # deferred on purpose: loads numba (compiled kernels) only where used
    from calibkit.core.geometry_kernels import mean_ray_distances, triangulate_points

    order = np.argsort(point, kind="stable")
    starts = np.zeros(n + 1, dtype=np.int64)
    np.cumsum(n_cams, out=starts[1:])
    xyz0 = np.full((n, 3), np.nan) if start is None else np.asarray(
        start, dtype=np.float64).reshape(n, 3)
    xyz, reproj = triangulate_points(
        starts, camera[order], np.ascontiguousarray(uv[order]),
        np.ascontiguousarray(origins[order]), np.ascontiguousarray(dirs[order]),
        np.ascontiguousarray(xyz0), int(iterations), arrays.R, arrays.t, arrays.fx,
        arrays.fy, arrays.cx, arrays.cy, arrays.skew, arrays.dist)
    bad = ~np.isfinite(xyz[:, 0])
    if ray_distance:
        ray = mean_ray_distances(starts, np.ascontiguousarray(origins[order]),
                                 np.ascontiguousarray(dirs[order]))
    else:
        ray = np.full(n, np.nan)
    ray[bad] = np.nan
    return Triangulation(xyz, reproj, ray, n_cams)


def rigid_fit(src: np.ndarray, dst: np.ndarray, weights: np.ndarray | None = None,
              scale: bool = False) -> tuple[np.ndarray, np.ndarray, float]:
    """(R, t, s) minimising sum w |s R src + t - dst|^2 (Kabsch/Umeyama).

    The reflection fix keeps R a proper rotation even when the best orthogonal map would be
    a mirror (noisy, nearly planar or degenerate marker sets).
    """
    src = np.asarray(src, dtype=np.float64).reshape(-1, 3)
    dst = np.asarray(dst, dtype=np.float64).reshape(-1, 3)
    w = np.ones(len(src)) if weights is None else np.asarray(weights, dtype=np.float64)
    w = w / w.sum()
    mu_s = w @ src
    mu_d = w @ dst
    a = src - mu_s
    b = dst - mu_d
    cov = (b * w[:, None]).T @ a
    U, S, Vt = np.linalg.svd(cov)
    D = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        D[2, 2] = -1.0
    R = U @ D @ Vt
    s = 1.0
    if scale:
        var_s = float(w @ np.sum(a * a, axis=1))
        s = float(np.sum(S * np.diag(D)) / var_s) if var_s > 0 else 1.0
    t = mu_d - s * R @ mu_s
    return R, t, s
