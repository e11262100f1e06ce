"""Compiled (numba) gating and triangulation of tracks: the tracker's per-frame hot path.

Why: per frame the tracker does a few hundred flops per (track, camera) pair; as numpy
array operations most of the time goes to call overheads (about sixty calls a frame). This
kernel does the same steps as Tracker._associate and Tracker._triangulate in one pass
(tests compare the two): reproject every prediction into every camera, take the blob that
is alone within the gate both ways, one Gauss-Newton step linearised at the prediction,
drop the worst observation when it does not fit and solve again.
"""

from __future__ import annotations

import numpy as np

from calibkit.core.jit import jit


@jit
def _project(R, t, fx, fy, cx, cy, skew, dist, c, X, J):
    """Pixel (u, v) and depth of X in camera c; d pixel / d X into J (2, 3)."""
    pc0 = R[c, 0, 0] * X[0] + R[c, 0, 1] * X[1] + R[c, 0, 2] * X[2] + t[c, 0]
    pc1 = R[c, 1, 0] * X[0] + R[c, 1, 1] * X[1] + R[c, 1, 2] * X[2] + t[c, 1]
    pc2 = R[c, 2, 0] * X[0] + R[c, 2, 1] * X[1] + R[c, 2, 2] * X[2] + t[c, 2]
    z = pc2 if abs(pc2) > 1e-12 else 1e-12
    iz = 1.0 / z
    x = pc0 * iz
    y = pc1 * iz
    k1, k2, p1, p2, k3 = dist[c, 0], dist[c, 1], dist[c, 2], dist[c, 3], dist[c, 4]
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    u = fx[c] * xd + skew[c] * yd + cx[c]
    v = fy[c] * yd + cy[c]
    dradial = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)
    j11 = radial + 2.0 * x * x * dradial + 2.0 * p1 * y + 6.0 * p2 * x
    j12 = 2.0 * x * y * dradial + 2.0 * p1 * x + 2.0 * p2 * y
    j22 = radial + 2.0 * y * y * dradial + 6.0 * p1 * y + 2.0 * p2 * x
    a11 = (fx[c] * j11 + skew[c] * j12) * iz
    a12 = (fx[c] * j12 + skew[c] * j22) * iz
    a21 = fy[c] * j12 * iz
    a22 = fy[c] * j22 * iz
    b13 = -(a11 * x + a12 * y)
    b23 = -(a21 * x + a22 * y)
    for k in range(3):
        J[0, k] = a11 * R[c, 0, k] + a12 * R[c, 1, k] + b13 * R[c, 2, k]
        J[1, k] = a21 * R[c, 0, k] + a22 * R[c, 1, k] + b23 * R[c, 2, k]
    return u, v, pc2


@jit
def _solve(H, g, out):
    """out = H^-1 g for a symmetric 3x3 H; returns trace(H^-1), or -1 if singular."""
    a, b, c = H[0, 0], H[0, 1], H[0, 2]
    d, e, f = H[1, 1], H[1, 2], H[2, 2]
    A = d * f - e * e
    B = c * e - b * f
    C = b * e - c * d
    det = a * A + b * B + c * C
    if abs(det) < 1e-30:
        return -1.0
    D = a * f - c * c
    E = b * c - a * e
    F = a * d - b * b
    inv = 1.0 / det
    out[0] = (A * g[0] + B * g[1] + C * g[2]) * inv
    out[1] = (B * g[0] + D * g[1] + E * g[2]) * inv
    out[2] = (C * g[0] + E * g[1] + F * g[2]) * inv
    return (A + D + F) * inv


@jit
def gate_and_solve(pred, gate, need, R, t, fx, fy, cx, cy, skew, dist, order, starts, uv,
                   outlier_px, two_view_px, area, track_area, merge_ratio, merge_margin_px,
                   ambiguous_px, min_cos_two_view):
    """Tracks (pred (T, 3), gate_px (T,), cameras needed (T,)) against the frame's blobs
    (uv (M, 2); `order` sorts them by camera, `starts` (C + 1) bound each camera's run).

    A track takes, in each camera, its nearest blob within its gate when that pairing is
    unambiguous both ways: every other blob within the track's gate is at least
    `ambiguous_px` farther from its reprojection, every other track whose gate holds the
    blob is at least `ambiguous_px` farther from it, and the blob is no other track's
    nearest (a blob nearest to two tracks is two markers merged, or one of them hidden:
    neither's). A point from two cameras whose rays meet closer to parallel or antiparallel
    than |cos| = `min_cos_two_view` is not taken (ok False): along the rays it is not
    determined. With blob areas (`area` (M,), empty if unknown) a blob larger
    than merge_ratio times the track's own marker image at its depth, plus merge_margin_px,
    is not its own either (a merged blob with one tracked marker in it). `track_area` (T,)
    is each track's marker size (blob area x depth^2 / fx^2, m^2; 0 while unknown), updated
    in place from the blobs it used.

    -> blobs (T, C) index or -1, explained (M,) bool, xyz (T, 3), ok (T,), n_used (T,),
       sigma (T,) position std per pixel of noise, merged (T, C) bool: the track's nearest
       blob in that camera was taken for a merged blob by its area."""
    T = pred.shape[0]
    C = starts.shape[0] - 1
    M = uv.shape[0]
    blobs = np.full((T, C), -1, np.int64)
    near = np.full((T, C), -1, np.int64)
    near_d = np.full((T, C), np.inf)  # px from the track's reprojection to its nearest blob
    second_d = np.full((T, C), np.inf)  # ... and to its second nearest within the gate
    per_blob = np.zeros(M, np.int64)  # tracks whose gate holds the blob
    nearest_of = np.zeros(M, np.int64)  # tracks whose nearest blob it is
    blob_d1 = np.full(M, np.inf)  # px to the blob's nearest track (within that track's gate)
    blob_d2 = np.full(M, np.inf)  # ... and to its second nearest
    blob_t1 = np.full(M, -1, np.int64)
    Js = np.zeros((T, C, 2, 3))
    res = np.zeros((T, C, 2))
    depth = np.zeros((T, C))
    merged = np.zeros((T, C), np.bool_)
    J = np.zeros((2, 3))
    sized = area.shape[0] == uv.shape[0] and merge_ratio > 0
    for i in range(T):
        g2 = gate[i] * gate[i]
        for c in range(C):
            u, v, z = _project(R, t, fx, fy, cx, cy, skew, dist, c, pred[i], J)
            if z <= 0 or starts[c] == starts[c + 1]:
                continue
            best, best_d, next_d = -1, np.inf, np.inf
            for k in range(starts[c], starts[c + 1]):
                m = order[k]
                du = u - uv[m, 0]
                dv = v - uv[m, 1]
                d2 = du * du + dv * dv
                if d2 <= g2:
                    d = np.sqrt(d2)
                    per_blob[m] += 1
                    if d < best_d:
                        best, best_d, next_d = m, d, best_d
                    elif d < next_d:
                        next_d = d
                    if d < blob_d1[m]:
                        blob_d2[m] = blob_d1[m]
                        blob_d1[m], blob_t1[m] = d, i
                    elif d < blob_d2[m]:
                        blob_d2[m] = d
            near_d[i, c] = best_d
            second_d[i, c] = next_d
            if best >= 0:
                nearest_of[best] += 1
            if best >= 0 and sized and track_area[i] > 0:
                expected = track_area[i] * fx[c] * fx[c] / (z * z)
                if area[best] > merge_ratio * expected + merge_margin_px:
                    merged[i, c] = True
                    best = -1
            near[i, c] = best
            depth[i, c] = z
            if best >= 0:
                Js[i, c] = J
                res[i, c, 0] = u - uv[best, 0]
                res[i, c, 1] = v - uv[best, 1]
    explained = per_blob > 0
    sizes = np.zeros(C)
    xyz = pred.copy()
    ok = np.zeros(T, np.bool_)
    n_used = np.zeros(T, np.int64)
    sigma = np.full(T, np.inf)
    H = np.zeros((3, 3))
    g = np.zeros(3)
    step = np.zeros(3)
    e = np.zeros(C)
    for i in range(T):
        for c in range(C):
            m = near[i, c]
            if m < 0 or nearest_of[m] != 1:
                continue
            d = near_d[i, c]
            other = blob_d2[m] if blob_t1[m] == i else blob_d1[m]
            if second_d[i, c] - d >= ambiguous_px and other - d >= ambiguous_px:
                blobs[i, c] = m
        for attempt in range(2):
            H[:, :] = 0.0
            g[:] = 0.0
            n = 0
            for c in range(C):
                if blobs[i, c] < 0:
                    continue
                n += 1
                for a in range(3):
                    g[a] += Js[i, c, 0, a] * res[i, c, 0] + Js[i, c, 1, a] * res[i, c, 1]
                    for b in range(3):
                        H[a, b] += Js[i, c, 0, a] * Js[i, c, 0, b] + Js[i, c, 1, a] * Js[i, c, 1, b]
            for a in range(3):
                H[a, a] += 1e-9
            tr = _solve(H, g, step)
            if tr < 0:
                n = 0
                break
            worst, worst_e = -1, -1.0
            for c in range(C):
                if blobs[i, c] < 0:
                    continue
                r0 = res[i, c, 0] - (Js[i, c, 0, 0] * step[0] + Js[i, c, 0, 1] * step[1]
                                     + Js[i, c, 0, 2] * step[2])
                r1 = res[i, c, 1] - (Js[i, c, 1, 0] * step[0] + Js[i, c, 1, 1] * step[1]
                                     + Js[i, c, 1, 2] * step[2])
                e[c] = np.sqrt(r0 * r0 + r1 * r1)
                if e[c] > worst_e:
                    worst_e, worst = e[c], c
            if attempt == 0 and worst_e > outlier_px and n > 2:
                blobs[i, worst] = -1
                continue
            break
        n_used[i] = n
        if n == 0:
            continue
        limit = min(outlier_px, two_view_px) if n == 2 else outlier_px
        good = n >= need[i]
        for c in range(C):
            if blobs[i, c] >= 0 and e[c] > limit:
                good = False
        for a in range(3):
            xyz[i, a] = pred[i, a] - step[a]
        if good and n == 2:
            good = _rays_apart(R, t, blobs[i], xyz[i], min_cos_two_view)
        ok[i] = good
        sigma[i] = np.sqrt(max(tr, 0.0) / 3.0)
        if sized and good:
            k = 0
            for c in range(C):
                if blobs[i, c] >= 0:
                    sizes[k] = area[blobs[i, c]] * depth[i, c] * depth[i, c] / (fx[c] * fx[c])
                    k += 1
            track_area[i] = learn_size(track_area[i], np.median(sizes[:k]))
    return blobs, explained, xyz, ok, n_used, sigma, merged


@jit
def _rays_apart(R, t, row, X, min_cos):
    """Whether the rays from the two cameras with a blob in `row` (C,) to X meet at an
    angle whose |cos| is below min_cos."""
    ray = np.zeros((2, 3))
    k = 0
    for c in range(row.shape[0]):
        if row[c] < 0 or k == 2:
            continue
        for a in range(3):  # X - centre, centre = -R^T t
            ray[k, a] = X[a] + R[c, 0, a] * t[c, 0] + R[c, 1, a] * t[c, 1] + R[c, 2, a] * t[c, 2]
        k += 1
    dot = ray[0, 0] * ray[1, 0] + ray[0, 1] * ray[1, 1] + ray[0, 2] * ray[1, 2]
    n0 = ray[0, 0] ** 2 + ray[0, 1] ** 2 + ray[0, 2] ** 2
    n1 = ray[1, 0] ** 2 + ray[1, 1] ** 2 + ray[1, 2] ** 2
    return dot * dot < min_cos * min_cos * n0 * n1


@jit
def learn_size(current, sample):
    """A track's marker size after one more frame's median over its cameras: the first
    sample as it is, then a slow geometric mean (a size is steady; one frame's merged or
    clipped blobs must not move it far)."""
    if current <= 0:
        return sample
    return np.exp(0.9 * np.log(current) + 0.1 * np.log(max(sample, 1e-30)))


@jit
def refine_step(R, t, markers, obs, uv, Rc, tc, fx, fy, cx, cy, skew, dist, valid):
    """One Gauss-Newton step on each valid body's pose against its markers' blobs (the
    compiled form of daemon.tracking.rigid.refine_poses; tests compare them). R (B, 3, 3) and
    t (B, 3) are updated in place."""
    B, K = markers.shape[0], markers.shape[1]
    C = obs.shape[2]
    J = np.zeros((2, 3))
    Jp = np.zeros((2, 6))
    H = np.zeros((6, 6))
    g = np.zeros(6)
    X = np.zeros(3)
    Rm = np.zeros(3)
    for b in range(B):
        if not valid[b]:
            continue
        H[:, :] = 0.0
        g[:] = 0.0
        n = 0
        for k in range(K):
            for a in range(3):
                Rm[a] = R[b, a, 0] * markers[b, k, 0] + R[b, a, 1] * markers[b, k, 1] \
                    + R[b, a, 2] * markers[b, k, 2]
                X[a] = Rm[a] + t[b, a]
            for c in range(C):
                m = obs[b, k, c]
                if m < 0:
                    continue
                u, v, z = _project(Rc, tc, fx, fy, cx, cy, skew, dist, c, X, J)
                if z <= 0:
                    continue
                r0 = u - uv[m, 0]
                r1 = v - uv[m, 1]
                # d X / d(rotation increment) = -[Rm]x ; d X / d t = I
                for i in range(2):
                    Jp[i, 0] = J[i, 2] * Rm[1] - J[i, 1] * Rm[2]
                    Jp[i, 1] = J[i, 0] * Rm[2] - J[i, 2] * Rm[0]
                    Jp[i, 2] = J[i, 1] * Rm[0] - J[i, 0] * Rm[1]
                    Jp[i, 3] = J[i, 0]
                    Jp[i, 4] = J[i, 1]
                    Jp[i, 5] = J[i, 2]
                for p in range(6):
                    g[p] += Jp[0, p] * r0 + Jp[1, p] * r1
                    for q in range(6):
                        H[p, q] += Jp[0, p] * Jp[0, q] + Jp[1, p] * Jp[1, q]
                n += 1
        if n < 6:
            continue
        step = -np.linalg.solve(H, g)
        angle = np.sqrt(step[0] ** 2 + step[1] ** 2 + step[2] ** 2)
        if angle > 1e-300:
            kx, ky, kz = step[0] / angle, step[1] / angle, step[2] / angle
        else:
            kx, ky, kz = 0.0, 0.0, 0.0
        s, c1 = np.sin(angle), 1.0 - np.cos(angle)
        dR = np.array([[1 - c1 * (ky * ky + kz * kz), -s * kz + c1 * kx * ky,
                        s * ky + c1 * kx * kz],
                       [s * kz + c1 * kx * ky, 1 - c1 * (kx * kx + kz * kz),
                        -s * kx + c1 * ky * kz],
                       [-s * ky + c1 * kx * kz, s * kx + c1 * ky * kz,
                        1 - c1 * (kx * kx + ky * ky)]])
        R[b] = dR @ R[b]
        for a in range(3):
            t[b, a] += step[3 + a]
