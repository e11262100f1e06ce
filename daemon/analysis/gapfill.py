"""Gap filling for labelled marker takes: rigid, spline, PCA and the seed's Newton fill.

A hidden marker leaves a gap (NaN samples between two seen ones). How best to fill it
depends on what else was seen: markers of the same near-rigid segment carry it along
(a rigid fit, as commercial "rigid body fill"); a short gap is smooth enough for a
spline; a long gap with the segment hidden is best predicted from how all markers move
together over the take (PCA). `fill` picks per gap and marks what it made up.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.interpolate import CubicSpline

from calibkit.core.blas import one_blas_thread
from daemon.formats.c3dio import Take
from daemon.labelling.markerset import MarkerSet

METHODS = ("auto", "linear", "cubic", "newton", "rigid", "pca")


@dataclass(frozen=True)
class Gap:
    marker: int
    start: int      # first missing frame
    stop: int       # first frame seen again (exclusive end)

    @property
    def length(self) -> int:
        return self.stop - self.start


def find_gaps(visible: np.ndarray, max_len: int | None = None) -> list[Gap]:
    """Interior gaps (seen before and after) per marker, shortest first excluded none."""
    gaps: list[Gap] = []
    F, n = visible.shape
    pad = np.zeros((1, n), bool)
    v = np.concatenate([pad, visible, pad]).astype(np.int8)
    d = np.diff(v, axis=0)
    for m in range(n):
        starts = np.nonzero(d[:, m] == -1)[0]   # frame where a hidden run begins
        stops = np.nonzero(d[:, m] == 1)[0]     # frame where a seen run begins
        for s in starts:
            after = stops[stops > s]
            if s == 0 or not len(after) or after[0] >= F:
                continue                         # before the first or after the last sample
            g = Gap(m, int(s), int(after[0]))
            if max_len is None or g.length <= max_len:
                gaps.append(g)
    return gaps


# ------------------------------------------------------------------ one gap, one method


def _window(x: np.ndarray, gap: Gap, half: int) -> tuple[np.ndarray, np.ndarray]:
    """Seen samples (t, xyz) of one marker within `half` frames either side of a gap."""
    lo, hi = max(0, gap.start - half), min(len(x), gap.stop + half)
    t = np.arange(lo, hi)
    ok = np.isfinite(x[lo:hi]).all(1)
    return t[ok], x[lo:hi][ok]


def fill_linear(x: np.ndarray, gap: Gap) -> np.ndarray:
    a, b = x[gap.start - 1], x[gap.stop]
    s = (np.arange(gap.start, gap.stop) - (gap.start - 1)) / (gap.length + 1)
    return a + s[:, None] * (b - a)


def fill_cubic(x: np.ndarray, gap: Gap, half: int = 30) -> np.ndarray:
    t, y = _window(x, gap, half)
    if len(t) < 4:
        return fill_linear(x, gap)
    return CubicSpline(t, y, axis=0)(np.arange(gap.start, gap.stop))


def _newton(t: np.ndarray, y: np.ndarray, tq: np.ndarray) -> np.ndarray:
    """Newton divided-difference interpolation through (t, y), evaluated at tq."""
    n = len(t)
    coef = y.astype(float).copy()
    for j in range(1, n):
        coef[j:] = (coef[j:] - coef[j - 1:-1]) / (t[j:] - t[:-j])[:, None]
    out = np.repeat(coef[-1:], len(tq), axis=0)
    for j in range(n - 2, -1, -1):
        out = out * (tq - t[j])[:, None] + coef[j]
    return out


def fill_newton(xyz: np.ndarray, gap: Gap, members: list[int], k: int = 2) -> np.ndarray:
    """The third seed's fill: the module's centre is interpolated with a Newton polynomial
    through k samples either side of the gap, and the marker keeps its offset from the
    centre as it was just before the gap (the previous shape carried along)."""
    m = gap.marker
    mates = [j for j in members if j != m]
    around = np.r_[gap.start - k:gap.start, gap.stop:gap.stop + k]
    around = around[(around >= 0) & (around < len(xyz))]
    tq = np.arange(gap.start, gap.stop)
    if mates:
        c = np.nanmean(xyz[:, mates], axis=1)          # module centre from the others
        ok = np.isfinite(c[around]).all(1)
        if ok.sum() >= 2 and np.isfinite(c[gap.start - 1]).all():
            centre = _newton(around[ok].astype(float), c[around[ok]], tq.astype(float))
            offset = xyz[gap.start - 1, m] - c[gap.start - 1]
            return centre + offset
    x = xyz[:, m]
    ok = np.isfinite(x[around]).all(1)
    return _newton(around[ok].astype(float), x[around[ok]], tq.astype(float))


def _kabsch_batch(A: np.ndarray, B: np.ndarray, w: np.ndarray):
    """Weighted rigid fits A[f] -> B[f] for a batch of frames: (F, k, 3) with weights
    (F, k). Returns R (F, 3, 3), ca (F, 3), cb (F, 3) so that x -> R (x - ca) + cb."""
    sw = w.sum(1)[:, None]
    A0, B0 = np.nan_to_num(A), np.nan_to_num(B)
    ca = (w[:, :, None] * A0).sum(1) / np.maximum(sw, 1e-12)
    cb = (w[:, :, None] * B0).sum(1) / np.maximum(sw, 1e-12)
    H = np.einsum("fk,fki,fkj->fij", w, A0 - ca[:, None], B0 - cb[:, None])
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(np.einsum("fji,fkj->fik", Vt, U)))
    D = np.ones((len(A), 3))
    D[:, 2] = d
    R = np.einsum("fji,fj,fkj->fik", Vt, D, U)
    return R, ca, cb


def fill_rigid(xyz: np.ndarray, gap: Gap, weights: np.ndarray, min_support: int = 3
               ) -> np.ndarray | None:
    """Carry the marker with the rigid motion of the other markers, each weighted by how
    steadily it keeps its distance to this one (`weights`, (n,)), fitted from each end of
    the gap to every gap frame and blended linearly in time. None when fewer than
    `min_support` well-weighted markers are seen at both ends and throughout."""
    m = gap.marker
    s0, s1 = gap.start - 1, gap.stop
    w = weights.copy()
    w[m] = 0.0
    ends = np.isfinite(xyz[[s0, s1]]).all(2).all(0)
    w = np.where(ends, w, 0.0)
    use = np.nonzero(w > 0)[0]
    if len(use) < min_support:
        return None
    inside = xyz[gap.start:gap.stop][:, use]                     # (L, k, 3)
    wf = np.isfinite(inside).all(2) * w[use][None]
    strong = (wf > 0).sum(1)
    if (strong < min_support).any():
        return None
    L = gap.length
    out = []
    for s in (s0, s1):
        A = np.repeat(xyz[s, use][None], L, axis=0)
        R, ca, cb = _kabsch_batch(A, inside, wf)
        out.append(np.einsum("fij,fj->fi", R, xyz[s, m] - ca) + cb)
    a = (np.arange(1, L + 1) / (L + 1))[:, None]
    return (1 - a) * out[0] + a * out[1]


# ------------------------------------------------------------------ PCA over the take


def pca_reconstruct(xyz: np.ndarray, energy: float = 0.995, iters: int = 30,
                    init: np.ndarray | None = None) -> np.ndarray:
    """Fill every missing sample from the correlations between markers over the take:
    iterative low-rank (PCA) imputation of the frames x (markers*3) matrix, in
    coordinates relative to each frame's centroid so that walking across the room does
    not use up the components."""
    with one_blas_thread():
        return _pca_iterations(xyz, energy, iters, init)


def _pca_iterations(xyz, energy, iters, init):
    F, n, _ = xyz.shape
    miss = ~np.isfinite(xyz)
    x = init.copy() if init is not None else _linear_everywhere(xyz)
    for _ in range(iters):
        cen = x.mean(1, keepdims=True)
        rel = (x - cen).reshape(F, -1)
        mu = rel.mean(0)
        U, S, Vt = np.linalg.svd(rel - mu, full_matrices=False)
        e = np.cumsum(S ** 2) / np.sum(S ** 2)
        r = int(np.searchsorted(e, energy) + 1)
        rec = (U[:, :r] * S[:r]) @ Vt[:r] + mu
        new = rec.reshape(F, n, 3) + cen
        change = np.abs(new[miss] - x[miss]).max() if miss.any() else 0.0
        x[miss] = new[miss]
        if change < 1e-5:
            break
    return x


def _linear_everywhere(xyz: np.ndarray) -> np.ndarray:
    """Every NaN replaced by linear interpolation in time (held at the ends)."""
    F, n, _ = xyz.shape
    out = xyz.copy()
    t = np.arange(F)
    for m in range(n):
        ok = np.isfinite(xyz[:, m]).all(1)
        if not ok.any():
            out[:, m] = 0.0
            continue
        for c in range(3):
            out[~ok, m, c] = np.interp(t[~ok], t[ok], xyz[ok, m, c])
    return out


# ------------------------------------------------------------------ the whole take


def fill(take: Take, ms: MarkerSet | None = None, max_gap_s: float | None = None,
         method: str = "auto") -> tuple[Take, dict]:
    """Fill the interior gaps of a take (up to max_gap_s long). Returns the filled take,
    with `filled` marking made-up samples, and a count of gaps per method used."""
    if method not in METHODS:
        raise ValueError(f"unknown method {method!r}")
    xyz = take.xyz_m.copy()
    vis = take.visible
    max_len = None if max_gap_s is None else int(round(max_gap_s * take.rate_hz))
    gaps = find_gaps(vis, max_len)
    seg_of, weights = _segments(take, ms)
    counts = {m: 0 for m in METHODS[1:]}
    pca = None
    short = int(round(0.15 * take.rate_hz))
    for g in gaps:
        mates = seg_of[g.marker]
        got = None
        how = method
        if method == "auto":
            how = _choose(take.xyz_m, g, weights[g.marker], short)
            if how == "rigid":
                got = fill_rigid(take.xyz_m, g, weights[g.marker])
        elif method == "rigid":
            got = fill_rigid(take.xyz_m, g, weights[g.marker])
            if got is None:
                how = "cubic"
        if got is None:
            if how == "linear":
                got = fill_linear(take.xyz_m[:, g.marker], g)
            elif how == "cubic":
                got = fill_cubic(take.xyz_m[:, g.marker], g)
            elif how == "newton":
                got = fill_newton(take.xyz_m, g, [g.marker, *mates])
            elif how == "pca":
                if pca is None:
                    pca = pca_reconstruct(take.xyz_m)
                got = _pca_bridge(take.xyz_m, pca, g)
        xyz[g.start:g.stop, g.marker] = got
        counts[how] += 1
    filled = take.filled.copy()
    filled |= np.isfinite(xyz).all(2) & ~vis
    return Take(list(take.labels), xyz, take.rate_hz, take.first_frame, filled,
                dict(take.meta)), counts


def _choose(xyz: np.ndarray, gap: Gap, weights: np.ndarray, short: int,
            trials: int = 3) -> str:
    """Pick the fill for one gap by trying rigid and spline fills on gaps of the same
    length cut where the marker was seen, nearest to this gap; PCA when the rigid fill
    has no support and the gap is long."""
    m, L = gap.marker, gap.length
    x = xyz[:, m]
    seen = np.isfinite(x).all(1)
    # starts s where frames s-1 .. s+L are all seen
    run = np.convolve(seen.astype(int), np.ones(L + 2, int), "valid") == L + 2
    starts = np.nonzero(run)[0] + 1
    rigid_ok = fill_rigid(xyz, gap, weights) is not None
    if not len(starts):
        return "rigid" if rigid_ok else ("cubic" if L <= short else "pca")
    near = starts[np.argsort(np.abs(starts - gap.start))[: 8 * trials]]
    picks = near[:: max(1, len(near) // trials)][:trials]
    err = {"rigid": 0.0, "cubic": 0.0}
    n_ok = 0
    for s in picks:
        test = Gap(m, int(s), int(s + L))
        truth = x[s:s + L].copy()
        cut = xyz.copy()
        cut[s:s + L, m] = np.nan
        r = fill_rigid(cut, test, weights)
        if r is None:
            continue
        c = fill_cubic(cut[:, m], test)
        err["rigid"] += float(np.sum((r - truth) ** 2))
        err["cubic"] += float(np.sum((c - truth) ** 2))
        n_ok += 1
    if not rigid_ok:
        return "cubic" if L <= short else "pca"
    if n_ok == 0:
        return "rigid"
    return min(err, key=err.get)


def _pca_bridge(xyz: np.ndarray, rec: np.ndarray, gap: Gap) -> np.ndarray:
    """The PCA reconstruction, corrected so it meets the seen samples at both ends (its
    offset there is removed linearly across the gap)."""
    m = gap.marker
    s0, s1 = gap.start - 1, gap.stop
    d0 = xyz[s0, m] - rec[s0, m]
    d1 = xyz[s1, m] - rec[s1, m]
    a = (np.arange(1, gap.length + 1) / (gap.length + 1))[:, None]
    return rec[gap.start:gap.stop, m] + (1 - a) * d0 + a * d1


def _segments(take: Take, ms: MarkerSet | None) -> tuple[list[list[int]], np.ndarray]:
    """For each marker of the take: the markers of its segment (the steadiest, for the
    Newton fill) and a weight for every other marker, 1 / (spread^2 + 3 mm^2), zero
    beyond a spread of 30 mm (for the rigid fill)."""
    n = len(take.labels)
    if ms is not None and all(lab in ms.labels for lab in take.labels):
        idx = [ms.labels.index(lab) for lab in take.labels]
        sd = ms.sd_m[np.ix_(idx, idx)]
    else:
        x = take.xyz_m
        step = max(1, take.n_frames // 400)
        d = np.linalg.norm(x[::step, :, None] - x[::step, None], axis=3)
        sd = np.nanstd(d, axis=0)
        sd = np.where(np.isfinite(sd), sd, np.inf)
    sd = sd.copy()
    np.fill_diagonal(sd, np.inf)
    members = []
    for m in range(n):
        order = np.argsort(sd[m])
        members.append([int(j) for j in order[:5] if sd[m, j] < 0.015])
    w = np.where(sd < 0.06, 1.0 / (sd ** 2 + 0.003 ** 2), 0.0)
    return members, w
