"""How a camera's detector turns the image discs of markers into blobs: overlapping discs
merge, a nearer marker covers part of a farther one.

Why it matters: two markers whose images overlap give one blob at neither marker's place,
the main real cause of identity swaps in tracking; a simulator that always reports every
marker apart hides that. Everything here is vectorised over all the markers of a whole
capture (minutes of frames): no loop per blob or per frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True, eq=False)
class MergedBlobs:
    """The blobs a detector makes of markers' image discs (one row per blob).

    uv: centroid (brightness x visible area weighted); area_px: the visible area (the union
    of the discs); peak: the brightest marker's; n_markers: markers that went into it;
    dominant: index (into the input rows) of the member that gave it most light;
    group: (N,) the blob each input row went into.
    """

    uv: np.ndarray
    area_px: np.ndarray
    peak: np.ndarray
    n_markers: np.ndarray
    dominant: np.ndarray
    group: np.ndarray


def overlapping_pairs(frame: np.ndarray, uv: np.ndarray, radius_px: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pairs (i, j, distance px) of discs of the same frame that overlap.

    A sweep along u: rows sorted by (frame, u) are compared with their s-th successor for
    s = 1, 2, ... while any successor of the same frame is still near enough in u to touch;
    each step is one vectorised comparison over all rows (no loop per disc, and no all-pairs
    table per frame)."""
    n = len(frame)
    if n < 2:
        z = np.zeros(0, dtype=np.int64)
        return z, z, np.zeros(0)
    # one sort key: frames apart by more than any image is wide, u within
    span = float(np.ptp(uv[:, 0])) + 1.0
    order = np.argsort((frame - frame.min()) * span * 2 + (uv[:, 0] - uv[:, 0].min()),
                       kind="stable")
    f, u, v, r = frame[order], uv[order, 0], uv[order, 1], radius_px[order]
    r_max = float(r.max())
    I, J, D = [], [], []
    for s in range(1, n):
        du = u[s:] - u[:-s]
        near = (du < r[:-s] + r_max) & (f[s:] == f[:-s])
        if not near.any():
            break
        k = np.flatnonzero(near)
        d = np.hypot(du[k], v[s:][k] - v[:-s][k])
        hit = d < r[k] + r[k + s]
        I.append(order[k[hit]])
        J.append(order[k[hit] + s])
        D.append(d[hit])
    if not I:
        z = np.zeros(0, dtype=np.int64)
        return z, z, np.zeros(0)
    return np.concatenate(I), np.concatenate(J), np.concatenate(D)


def _lens(r1: np.ndarray, r2: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Area of the overlap of discs of radius r1 and r2 whose centres are d apart, and the
    distance of its centroid from the first centre along the line to the second."""
    d = np.maximum(d, 1e-12)
    inside = d <= np.abs(r1 - r2)
    # the chord's distance from each centre (a from the first, b from the second)
    a = np.clip((d * d + r1 * r1 - r2 * r2) / (2 * d), -r1, r1)
    b = np.clip(d - a, -r2, r2)
    h1 = np.sqrt(np.maximum(r1 * r1 - a * a, 0.0))
    h2 = np.sqrt(np.maximum(r2 * r2 - b * b, 0.0))
    s1 = r1 * r1 * np.arccos(a / r1) - a * h1  # the first disc's part beyond the chord
    s2 = r2 * r2 * np.arccos(b / r2) - b * h2  # the second's on the first's side
    area = s1 + s2
    # a disc segment's centroid lies (2/3) h^3 / S from its centre
    x1 = 2.0 * h1**3 / (3.0 * np.maximum(s1, 1e-300))
    x2 = d - 2.0 * h2**3 / (3.0 * np.maximum(s2, 1e-300))
    centre = (s1 * x1 + s2 * x2) / np.maximum(area, 1e-300)
    small = np.minimum(r1, r2)
    area = np.where(inside, np.pi * small * small, area)
    centre = np.where(inside, np.where(r1 <= r2, 0.0, d), centre)
    return area, centre


_DISC_SAMPLES = (lambda g: g[np.hypot(g[:, 0], g[:, 1]) < 1.0])(
    np.stack(np.meshgrid(np.arange(-31, 32, 2) / 32, np.arange(-31, 32, 2) / 32),
             axis=-1).reshape(-1, 2))  # a regular grid over the unit disc (~800 points)


def _visible_part(rows: np.ndarray, near: np.ndarray, far: np.ndarray, uv: np.ndarray,
                  radius: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(area, first moment (N, 2)) of the parts of discs `rows` that no nearer disc covers,
    sampled on a regular grid: for markers under two or more nearer discs, whose lenses may
    overlap (rare: the pairwise lens is exact for one)."""
    pick = np.isin(far, rows)
    f, n = np.searchsorted(rows, far[pick]), near[pick]
    pts = uv[rows][:, None, :] + radius[rows][:, None, None] * _DISC_SAMPLES[None]  # (R, S, 2)
    d2 = np.sum((pts[f] - uv[n][:, None, :]) ** 2, axis=2)  # (pairs, S)
    hidden = np.zeros(pts.shape[:2], dtype=bool)
    np.logical_or.at(hidden, f, d2 < radius[n][:, None] ** 2)
    cell = np.pi * radius[rows] ** 2 / len(_DISC_SAMPLES)
    shown = ~hidden
    area = shown.sum(axis=1) * cell
    moment = np.sum(pts * shown[..., None], axis=1) * cell[:, None]
    return area, moment


def merge_blobs(frame: np.ndarray, uv: np.ndarray, radius_px: np.ndarray, depth: np.ndarray,
                peak: np.ndarray, separate: bool = False) -> MergedBlobs:
    """What a detector makes of markers' image discs (rows: one marker in one frame of one
    camera): a marker partly covered by a nearer one shows only its uncovered part, so its
    light comes from a centre shifted away from the covered side; discs that overlap form
    one thresholded region, one blob whose centroid is the brightness x area weighted mean
    of its markers' visible parts and whose area is their union (never less than the larger
    disc). With `separate` (a multi-threshold detector) overlapping markers stay apart
    while each keeps its own brightest point, i.e. unless a marker's centre lies under a
    nearer disc.

    Vectorised over all rows at once: overlapping pairs by a sweep (overlapping_pairs), the
    covered parts as disc lenses, the groups as connected components, the sums by bincount.
    """
    # deferred on purpose: loads SciPy's sparse graphs only where used
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    n = len(frame)
    uv = np.asarray(uv, dtype=np.float64).reshape(n, 2)
    area = np.pi * radius_px**2
    i, j, d = overlapping_pairs(frame, uv, radius_px)
    if not len(i):  # nothing touches: every marker is a blob of its own
        every = np.arange(n)
        return MergedBlobs(uv.copy(), area, np.asarray(peak, dtype=np.float64).copy(),
                           np.ones(n, dtype=np.int64), every, every)
    # only markers that touch another need more than a copy: work on those rows alone
    rows = np.unique(np.concatenate([i, j]))
    i, j = np.searchsorted(rows, i), np.searchsorted(rows, j)
    m = len(rows)
    r_t, uv_t, area_t, peak_t = radius_px[rows], uv[rows], area[rows], peak[rows]
    # the nearer of each pair covers part of the farther
    swap = depth[rows][i] > depth[rows][j]
    near, far = np.where(swap, j, i), np.where(swap, i, j)
    lens_area, lens_at = _lens(r_t[far], r_t[near], d)
    direction = (uv_t[near] - uv_t[far]) / np.maximum(d, 1e-12)[:, None]
    lens_uv = uv_t[far] + lens_at[:, None] * direction
    visible = np.maximum(area_t - np.bincount(far, lens_area, minlength=m), 0.0)
    moment = area_t[:, None] * uv_t
    moment[:, 0] -= np.bincount(far, lens_area * lens_uv[:, 0], minlength=m)
    moment[:, 1] -= np.bincount(far, lens_area * lens_uv[:, 1], minlength=m)
    several = np.flatnonzero(np.bincount(far, minlength=m) > 1)
    if len(several):  # lenses that overlap each other: measure the visible part directly
        visible[several], moment[several] = _visible_part(several, near, far, uv_t, r_t)
    visible = np.where(visible < 0.02 * area_t, 0.0, visible)  # wholly covered: no light
    centre = np.where(visible[:, None] > 0, moment / np.maximum(visible, 1e-300)[:, None],
                      uv_t)
    # several nearer discs over one marker: their lenses may overlap and be taken off
    # twice; the visible part's centre still lies within the marker's disc
    shift = centre - uv_t
    norm = np.hypot(shift[:, 0], shift[:, 1])
    centre = uv_t + shift * np.minimum(1.0, r_t / np.maximum(norm, 1e-300))[:, None]
    join = d < r_t[near] if separate else np.ones(len(d), dtype=bool)
    graph = coo_matrix((np.ones(int(join.sum())), (near[join], far[join])), shape=(m, m))
    n_groups, g = connected_components(graph, directed=False)
    light = peak_t * visible
    total = np.bincount(g, light, minlength=n_groups)
    g_uv = np.stack([np.bincount(g, light * centre[:, 0], minlength=n_groups),
                     np.bincount(g, light * centre[:, 1], minlength=n_groups)], axis=1)
    g_uv /= np.maximum(total, 1e-300)[:, None]
    g_area = np.bincount(g, visible, minlength=n_groups)
    by_light = np.lexsort((-light, g))  # each group's brightest member first
    head = by_light[np.flatnonzero(np.r_[True, np.diff(g[by_light]) != 0])]
    by_area = np.lexsort((-area_t, g))
    biggest = area_t[by_area[np.flatnonzero(np.r_[True, np.diff(g[by_area]) != 0])]]
    by_peak = np.lexsort((-peak_t, g))
    g_peak = peak_t[by_peak[np.flatnonzero(np.r_[True, np.diff(g[by_peak]) != 0])]]
    if not separate:  # one region: the union of the discs, at least the larger disc
        g_area = np.maximum(g_area, biggest)
    # every other marker is a blob of its own, as it is
    alone = np.ones(n, dtype=bool)
    alone[rows] = False
    lone = np.flatnonzero(alone)
    group = np.empty(n, dtype=np.int64)
    group[lone] = np.arange(len(lone))
    group[rows] = len(lone) + g
    return MergedBlobs(np.concatenate([uv[lone], g_uv]),
                       np.concatenate([area[lone], g_area]),
                       np.concatenate([peak[lone], g_peak]),
                       np.concatenate([np.ones(len(lone), dtype=np.int64),
                                       np.bincount(g, minlength=n_groups)]),
                       np.concatenate([lone, rows[head]]), group)
