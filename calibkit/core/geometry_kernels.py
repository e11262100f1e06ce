"""Compiled (numba) kernels for the per-point loops of triangulation and correspondence.

Why: these loops do a few dozen flops per point or blob pair; as numpy array operations
the time goes to call overheads, not arithmetic. The numpy implementations in geometry.py
and correspondence.py stay as the reference the tests compare these against.

Conventions as in calibkit.core.geometry: cameras are stacked arrays (R (C,3,3) world-to-camera,
t (C,3), intrinsics fx fy cx cy skew (C,), dist (C,5) OpenCV k1 k2 p1 p2 k3).
"""

from __future__ import annotations

import numpy as np

from calibkit.core.jit import jit


@jit(inline="always")
def _project_jacobian(R, t, fx, fy, cx, cy, skew, dist, c, X, out_uv, out_J):
    """Project world point X with camera c; pixel in out_uv (2,), d pixel / d X in out_J
    (2,3). Returns the depth."""
    pc0 = R[c, 0, 0] * X[0] + R[c, 0, 1] * X[1] + R[c, 0, 2] * X[2] + t[c, 0]
    pc1 = R[c, 1, 0] * X[0] + R[c, 1, 1] * X[1] + R[c, 1, 2] * X[2] + t[c, 1]
    pc2 = R[c, 2, 0] * X[0] + R[c, 2, 1] * X[1] + R[c, 2, 2] * X[2] + t[c, 2]
    z = pc2 if abs(pc2) > 1e-12 else 1e-12
    x = pc0 / z
    y = pc1 / z
    k1, k2, p1, p2, k3 = dist[c, 0], dist[c, 1], dist[c, 2], dist[c, 3], dist[c, 4]
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    out_uv[0] = fx[c] * xd + skew[c] * yd + cx[c]
    out_uv[1] = fy[c] * yd + cy[c]
    dradial = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)
    j11 = radial + 2.0 * x * x * dradial + 2.0 * p1 * y + 6.0 * p2 * x
    j12 = 2.0 * x * y * dradial + 2.0 * p1 * x + 2.0 * p2 * y
    j22 = radial + 2.0 * y * y * dradial + 6.0 * p1 * y + 2.0 * p2 * x
    a11 = fx[c] * j11 + skew[c] * j12
    a12 = fx[c] * j12 + skew[c] * j22
    a21 = fy[c] * j12
    a22 = fy[c] * j22
    inv_z = 1.0 / z
    b0 = a11 * inv_z
    b1 = a12 * inv_z
    b2 = -(a11 * x + a12 * y) * inv_z
    d0 = a21 * inv_z
    d1 = a22 * inv_z
    d2 = -(a21 * x + a22 * y) * inv_z
    for k in range(3):
        out_J[0, k] = b0 * R[c, 0, k] + b1 * R[c, 1, k] + b2 * R[c, 2, k]
        out_J[1, k] = d0 * R[c, 0, k] + d1 * R[c, 1, k] + d2 * R[c, 2, k]
    return pc2


@jit(inline="always")
def _solve3(H, g, out):
    """out = H^-1 g for a 3x3 H; False when singular."""
    a, b, c = H[0, 0], H[0, 1], H[0, 2]
    d, e, f = H[1, 0], H[1, 1], H[1, 2]
    gg, h, i = H[2, 0], H[2, 1], H[2, 2]
    co0 = e * i - f * h
    co1 = f * gg - d * i
    co2 = d * h - e * gg
    det = a * co0 + b * co1 + c * co2
    scale = 0.0
    for r in range(3):
        for s in range(3):
            scale = max(scale, abs(H[r, s]))
    if not (abs(det) > 1e-18 * max(1.0, scale) ** 3) or not np.isfinite(det):
        return False
    x, y, z = g[0], g[1], g[2]
    out[0] = (co0 * x + (c * h - b * i) * y + (b * f - c * e) * z) / det
    out[1] = (co1 * x + (a * i - c * gg) * y + (c * d - a * f) * z) / det
    out[2] = (co2 * x + (b * gg - a * h) * y + (a * e - b * d) * z) / det
    return True


@jit
def triangulate_points(starts, camera, uv, origins, dirs, xyz0, iterations,
                       R, t, fx, fy, cx, cy, skew, dist):
    """Triangulate points whose observations are rows starts[p]:starts[p+1] (sorted by point).

    Start: xyz0[p] where finite, else the least-squares point nearest to the rays. Then
    `iterations` Gauss-Newton steps on the reprojection error. Returns xyz (P,3) (NaN for
    < 2 observations, singular systems or a point behind one of its cameras) and the RMS
    reprojection error per point."""
    n_points = len(starts) - 1
    xyz = np.full((n_points, 3), np.nan)
    reproj = np.full(n_points, np.nan)
    H = np.zeros((3, 3))
    g = np.zeros(3)
    step = np.zeros(3)
    p_uv = np.zeros(2)
    J = np.zeros((2, 3))
    X = np.zeros(3)
    for p in range(n_points):
        s, e = starts[p], starts[p + 1]
        if e - s < 2:
            continue
        if np.isfinite(xyz0[p, 0]) and np.isfinite(xyz0[p, 1]) and np.isfinite(xyz0[p, 2]):
            X[0], X[1], X[2] = xyz0[p, 0], xyz0[p, 1], xyz0[p, 2]
        else:
            H[:, :] = 0.0
            g[:] = 0.0
            for m in range(s, e):
                for r in range(3):
                    for q in range(3):
                        P = (1.0 if r == q else 0.0) - dirs[m, r] * dirs[m, q]
                        H[r, q] += P
                        g[r] += P * origins[m, q]
            if not _solve3(H, g, X):
                continue
        ok = True
        for _ in range(iterations):
            H[:, :] = 0.0
            g[:] = 0.0
            for m in range(s, e):
                _project_jacobian(R, t, fx, fy, cx, cy, skew, dist, camera[m], X, p_uv, J)
                r0 = p_uv[0] - uv[m, 0]
                r1 = p_uv[1] - uv[m, 1]
                for a in range(3):
                    g[a] += J[0, a] * r0 + J[1, a] * r1
                    for b in range(3):
                        H[a, b] += J[0, a] * J[0, b] + J[1, a] * J[1, b]
            if _solve3(H, g, step):
                X[0] -= step[0]
                X[1] -= step[1]
                X[2] -= step[2]
        sq = 0.0
        for m in range(s, e):
            depth = _project_jacobian(R, t, fx, fy, cx, cy, skew, dist, camera[m], X, p_uv, J)
            if not depth > 0:
                ok = False
            sq += (p_uv[0] - uv[m, 0]) ** 2 + (p_uv[1] - uv[m, 1]) ** 2
        if ok and np.isfinite(X[0]) and np.isfinite(X[1]) and np.isfinite(X[2]):
            xyz[p, 0], xyz[p, 1], xyz[p, 2] = X[0], X[1], X[2]
            reproj[p] = np.sqrt(sq / (e - s))
    return xyz, reproj


@jit
def epipolar_pairs(block_start, block_camera, block_group, lines, homog, origins, dirs,
                   tol_px, capacity):
    """Blob pairs (a, b) of one group in different cameras whose epipolar distances are
    below tol_px in both images, with the depths s, u along each ray where they pass
    closest (both in front).

    Blobs are sorted by (group, camera); block k holds the rows block_start[k] to
    block_start[k+1]-1, all of camera block_camera[k] and group block_group[k].
    lines[m, c] is blob m's epipolar line in camera c, scaled so that its dot product with
    a normalised homogeneous point of camera c is a distance in c's pixels. Returns the
    number of pairs; only the first `capacity` are stored (call again with more room)."""
    pa = np.empty(capacity, dtype=np.int64)
    pb = np.empty(capacity, dtype=np.int64)
    ss = np.empty(capacity)
    uu = np.empty(capacity)
    n = 0
    n_blocks = len(block_camera)
    for ka in range(n_blocks):
        ca = block_camera[ka]
        for kb in range(ka + 1, n_blocks):
            if block_group[kb] != block_group[ka]:
                break
            cb = block_camera[kb]
            for a in range(block_start[ka], block_start[ka + 1]):
                la0, la1, la2 = lines[a, cb, 0], lines[a, cb, 1], lines[a, cb, 2]
                for b in range(block_start[kb], block_start[kb + 1]):
                    dj = abs(la0 * homog[b, 0] + la1 * homog[b, 1] + la2 * homog[b, 2])
                    if dj >= tol_px:
                        continue
                    di = abs(lines[b, ca, 0] * homog[a, 0] + lines[b, ca, 1] * homog[a, 1]
                             + lines[b, ca, 2] * homog[a, 2])
                    if di >= tol_px:
                        continue
                    bb = 0.0
                    d_ = 0.0
                    e_ = 0.0
                    for k in range(3):
                        w = origins[a, k] - origins[b, k]
                        bb += dirs[a, k] * dirs[b, k]
                        d_ += dirs[a, k] * w
                        e_ += dirs[b, k] * w
                    denom = max(1.0 - bb * bb, 1e-12)
                    s = (bb * e_ - d_) / denom
                    u = (e_ - bb * d_) / denom
                    if s > 0 and u > 0:
                        if n < capacity:
                            pa[n] = a
                            pb[n] = b
                            ss[n] = s
                            uu[n] = u
                        n += 1
    return n, pa, pb, ss, uu


@jit
def mean_ray_distances(starts, origins, dirs):
    """Mean distance between every pair of each point's rays (rows starts[p]:starts[p+1]);
    NaN for points with fewer than two rays. Nearly parallel rays use the distance of one
    origin from the other line."""
    n_points = len(starts) - 1
    out = np.full(n_points, np.nan)
    for p in range(n_points):
        s, e = starts[p], starts[p + 1]
        total = 0.0
        count = 0
        for i in range(s, e):
            for j in range(i + 1, e):
                c0 = dirs[i, 1] * dirs[j, 2] - dirs[i, 2] * dirs[j, 1]
                c1 = dirs[i, 2] * dirs[j, 0] - dirs[i, 0] * dirs[j, 2]
                c2 = dirs[i, 0] * dirs[j, 1] - dirs[i, 1] * dirs[j, 0]
                norm = np.sqrt(c0 * c0 + c1 * c1 + c2 * c2)
                w0 = origins[j, 0] - origins[i, 0]
                w1 = origins[j, 1] - origins[i, 1]
                w2 = origins[j, 2] - origins[i, 2]
                if norm > 1e-9:
                    total += abs(w0 * c0 + w1 * c1 + w2 * c2) / norm
                else:
                    along = w0 * dirs[i, 0] + w1 * dirs[i, 1] + w2 * dirs[i, 2]
                    a0 = w0 - along * dirs[i, 0]
                    a1 = w1 - along * dirs[i, 1]
                    a2 = w2 - along * dirs[i, 2]
                    total += np.sqrt(a0 * a0 + a1 * a1 + a2 * a2)
                count += 1
        if count:
            out[p] = total / count
    return out
