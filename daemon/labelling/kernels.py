"""Compiled kernels for the labeller's per-frame steps (daemon/labelling/labeller.py).

The labeller works on 41 markers and a few dozen points per frame: numpy's per-call
overhead, not arithmetic, is what costs there, so the steps that run every frame are
plain loops compiled with numba (calibkit.core.jit). Each kernel has a numpy twin in
the labeller's modules (labeller, neighbours, reid, repair) that says
what it computes; tests/test_label.py checks they agree.
"""

from __future__ import annotations

import numpy as np

from calibkit.core.jit import jit


@jit
def _finite3(x) -> bool:
    return np.isfinite(x[0]) and np.isfinite(x[1]) and np.isfinite(x[2])


@jit
def _dist3(a, b) -> float:
    """Distance between two points (3,), without numpy's per-call overhead."""
    dx = a[0] - b[0]
    dy = a[1] - b[1]
    dz = a[2] - b[2]
    return np.sqrt(dx * dx + dy * dy + dz * dz)


@jit
def structure_error(cur, nb, nb_mean, tol):
    """Per marker: mean over its labelled neighbours of |d - mean| / tolerance, each
    capped at 3; NaN for a marker or with no labelled neighbour."""
    n, K = nb.shape
    out = np.full(n, np.nan)
    for i in range(n):
        if not _finite3(cur[i]):
            continue
        s = 0.0
        c = 0
        for k in range(K):
            j = nb[i, k]
            if not _finite3(cur[j]):
                continue
            e = abs(_dist3(cur[i], cur[j]) - nb_mean[i, k]) / tol[i, k]
            s += min(e, 3.0)
            c += 1
        if c:
            out[i] = s / c
    return out


@jit
def candidate_error(markers, P, cur, nb, nb_mean, tol):
    """(L, k) for markers x points: the mean capped neighbour-distance error (as
    `structure_error`) if the marker took the point, the number of labelled neighbours,
    and the sum of squared errors in SD units (tolerance / 3), each capped at 16."""
    L = len(markers)
    k = len(P)
    K = nb.shape[1]
    mean = np.zeros((L, k))
    num = np.zeros((L, k), np.int64)
    chi2 = np.zeros((L, k))
    for a in range(L):
        m = markers[a]
        for b in range(k):
            s = 0.0
            q = 0.0
            c = 0
            for kk in range(K):
                j = nb[m, kk]
                if not _finite3(cur[j]):
                    continue
                e = abs(_dist3(P[b], cur[j]) - nb_mean[m, kk]) / tol[m, kk]
                s += min(e, 3.0)
                q += min(9.0 * e * e, 16.0)
                c += 1
            num[a, b] = c
            mean[a, b] = s / max(c, 1)
            chi2[a, b] = q
    return mean, num, chi2


@jit
def predict_from_neighbours(A, B, W, Wmax, sd2, last, fallback):
    """Weighted Kabsch per lost marker l: the rigid motion from its snapshot A[l] (n, 3)
    to now B (n, 3), weights W[l] where both are seen, applied to `last` (L, 3). Fewer
    than 3 supporting markers (weight > 5 % of Wmax[l]) or a degenerate fit: translation
    only; no support at all: `fallback` (L, 3). Returns predictions and the weighted
    spread sqrt(sum w sd2 / sum w) of the markers used."""
    L, n = W.shape
    pred = np.empty((L, 3))
    spread = np.empty(L)
    okB = np.empty(n, np.bool_)
    for j in range(n):
        okB[j] = _finite3(B[j])
    for li in range(L):
        sw = 0.0
        ca = np.zeros(3)
        cb = np.zeros(3)
        s2 = 0.0
        support = 0
        for j in range(n):
            if not okB[j] or not _finite3(A[li, j]):
                continue
            w = W[li, j]
            if w > 0.05 * Wmax[li]:
                support += 1
            sw += w
            s2 += w * sd2[li, j]
            for c in range(3):
                ca[c] += w * A[li, j, c]
                cb[c] += w * B[j, c]
        den = max(sw, 1e-12)
        spread[li] = np.sqrt(s2 / den)
        if sw <= 0:
            pred[li] = fallback[li]
            continue
        ca /= den
        cb /= den
        H = np.zeros((3, 3))
        for j in range(n):
            if not okB[j] or not _finite3(A[li, j]):
                continue
            w = W[li, j]
            for r in range(3):
                ar = A[li, j, r] - ca[r]
                for c in range(3):
                    H[r, c] += w * ar * (B[j, c] - cb[c])
        R = np.eye(3)
        if support >= 3:
            U, S, Vt = np.linalg.svd(H)
            if S[1] > 1e-12 * max(S[0], 1e-30):
                V = Vt.T.copy()
                if np.linalg.det(V @ U.T) < 0:
                    V[:, 2] = -V[:, 2]
                R = V @ U.T
        d = last[li] - ca
        for r in range(3):
            pred[li, r] = R[r, 0] * d[0] + R[r, 1] * d[1] + R[r, 2] * d[2] + cb[r]
    return pred, spread


@jit
def rigid_residuals(shape, X, w, proper):
    """Squared residuals (H, m) of the weighted best rigid fit of shape[h] (m, 3) to X[h]
    (m, 3), weights w[h] (0 = not there); proper rotations only when `proper`."""
    Hn, m, _ = X.shape
    out = np.zeros((Hn, m))
    for h in range(Hn):
        sw = 0.0
        cs = np.zeros(3)
        cx = np.zeros(3)
        for i in range(m):
            wi = w[h, i]
            sw += wi
            for c in range(3):
                cs[c] += wi * shape[h, i, c]
                cx[c] += wi * X[h, i, c]
        den = max(sw, 1e-12)
        cs /= den
        cx /= den
        M = np.zeros((3, 3))
        for i in range(m):
            wi = w[h, i]
            if wi == 0:
                continue
            for r in range(3):
                sr = shape[h, i, r] - cs[r]
                for c in range(3):
                    M[r, c] += wi * sr * (X[h, i, c] - cx[c])
        U, S, Vt = np.linalg.svd(M)
        V = Vt.T.copy()
        if proper and np.linalg.det(V @ U.T) < 0:
            V[:, 2] = -V[:, 2]
        R = V @ U.T
        for i in range(m):
            wi = w[h, i]
            if wi == 0:
                continue
            e = 0.0
            for r in range(3):
                f = (R[r, 0] * (shape[h, i, 0] - cs[0]) + R[r, 1] * (shape[h, i, 1] - cs[1])
                     + R[r, 2] * (shape[h, i, 2] - cs[2]))
                g = f - (X[h, i, r] - cx[r])
                e += g * g
            out[h, i] = e * wi
    return out


@jit
def fresh_cost(markers, P, cur, anchors, tol_all, mean_all, margin, big):
    """(M, k): for markers never seen (or lost long), the steadiness-weighted mean of
    each point's squared distance errors to every labelled marker (chi2 / 9, each capped
    at 16); `big` where fewer than 3 labelled anchors, where the cost is 1 or more, and
    for a marker whose best point is not `margin` better than its second best."""
    M = len(markers)
    k = len(P)
    n = len(cur)
    out = np.full((M, k), big)
    seen = np.empty(n, np.bool_)
    n_seen = 0
    for j in range(n):
        seen[j] = _finite3(cur[j])
        n_seen += seen[j]
    if n_seen < 3:
        return out
    A = anchors.shape[1]
    for a in range(M):
        m = markers[a]
        sw = 0.0
        n_ok = 0
        for t in range(A):
            j = anchors[m, t]
            if seen[j]:
                n_ok += 1
                sw += 1.0 / (tol_all[m, j] * tol_all[m, j])
        if n_ok < 3:
            continue
        den = max(sw, 1e-12)
        for b in range(k):
            s = 0.0
            for t in range(A):
                j = anchors[m, t]
                if not seen[j]:
                    continue
                w = 1.0 / (tol_all[m, j] * tol_all[m, j])
                e = _dist3(P[b], cur[j]) - mean_all[m, j]
                s += min(e * e * w * 9.0, 16.0) * w
            c = s / den
            if c < 1.0:
                out[a, b] = c
        if k >= 2:
            b1 = big
            b2 = big
            for b in range(k):
                v = out[a, b]
                if v < b1:
                    b2 = b1
                    b1 = v
                elif v < b2:
                    b2 = v
            if b2 < b1 + margin:
                for b in range(k):
                    out[a, b] = big
    return out


@jit
def swap_scores(cur, I, J, swap_w, mean_all, witness):
    """For pairs (I[p], J[p]) of labelled markers: the weighted squared distance errors
    to every other labelled marker that may witness (`witness`) as labelled (keep) and
    with the two swapped (swap)."""
    p = len(I)
    n = len(cur)
    keep = np.zeros(p)
    swap = np.zeros(p)
    seen = np.empty(n, np.bool_)
    for x in range(n):
        seen[x] = _finite3(cur[x]) and witness[x]
    for q in range(p):
        i = I[q]
        j = J[q]
        for x in range(n):
            if not seen[x]:
                continue
            wi = swap_w[i, x] if x != j else 0.0
            wj = swap_w[j, x] if x != i else 0.0
            if wi == 0.0 and wj == 0.0:
                continue
            di = _dist3(cur[i], cur[x])
            dj = _dist3(cur[j], cur[x])
            mi = mean_all[i, x]
            mj = mean_all[j, x]
            keep[q] += wi * (di - mi) ** 2 + wj * (dj - mj) ** 2
            swap[q] += wi * (dj - mi) ** 2 + wj * (di - mj) ** 2
    return keep, swap


@jit
def module_candidates(markers, mates, cur, P, mean_all, tol_all, cand):
    """Widen `cand` (L, k) (points each lost module marker may take): with 2+ of its
    module mates labelled, also every point whose distances to all of them fit."""
    L = len(markers)
    k = len(P)
    n = len(cur)
    out = cand.copy()
    for a in range(L):
        x = markers[a]
        c = 0
        for y in range(n):
            if mates[x, y] and _finite3(cur[y]):
                c += 1
        if c < 2:
            continue
        for b in range(k):
            if out[a, b]:
                continue
            ok = True
            for y in range(n):
                if not mates[x, y] or not _finite3(cur[y]):
                    continue
                d = _dist3(P[b], cur[y])
                if abs(d - mean_all[x, y]) > tol_all[x, y]:
                    ok = False
                    break
            out[a, b] = ok
    return out


@jit
def commit_state(cur, has, pos, vel, age, snap, since, nb, smooth, steps):
    """Advance the tracker's state in place with this frame's labelled positions: the
    velocity of markers seen twice in a row (smoothed), a found-again marker takes its
    labelled neighbours' mean velocity, snapshots renewed for markers seen twice in a
    row (or never snapshotted), positions and ages; `steps` frames passed since the
    previous update (a live stage that fell behind). Returns the markers seen in the
    previous update and this one."""
    n = len(cur)
    seen_prev = np.zeros(n, np.bool_)
    for i in range(n):
        seen_prev[i] = has[i] and age[i] == 0
    for i in range(n):
        if seen_prev[i]:
            for c in range(3):
                vel[i, c] = smooth * (cur[i, c] - pos[i, c]) / steps + \
                    (1.0 - smooth) * vel[i, c]
        elif has[i]:
            vel[i] = 0.0
    K = nb.shape[1]
    re_vel = np.zeros((n, 3))
    for i in range(n):
        if has[i] and not seen_prev[i]:
            c = 0
            for k in range(K):
                j = nb[i, k]
                if has[j]:
                    c += 1
                    for d in range(3):
                        re_vel[i, d] += vel[j, d]
            for d in range(3):
                re_vel[i, d] /= max(c, 1)
    for i in range(n):
        if has[i] and not seen_prev[i]:
            vel[i] = re_vel[i]
            since[i] = 0
        else:
            since[i] += steps
        if not _finite3(vel[i]):
            vel[i] = 0.0
        steady = seen_prev[i] or (has[i] and not _finite3(snap[i, i]))
        if has[i]:
            pos[i] = cur[i]
            age[i] = 0
        else:
            age[i] += steps
        if steady:
            snap[i] = cur
    return seen_prev
