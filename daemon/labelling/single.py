"""Labelling one frame from the marker set alone, by growing labels from a segment.

The steadiest multi-marker segments are matched by their pairwise distances (each
fitting assignment is a hypothesis), every hypothesis grows one marker at a time (the
marker whose best point stands out most from its second best), and the handedness
tetrahedra pick between a body and its mirror image. This is what the live labeller
starts from when it has a single frame; a whole take starts from a window of frames
(start), which is more reliable on a body the set was not learned on.
"""

from __future__ import annotations

import numpy as np

from daemon.labelling.markerset import MarkerSet, signed_volume
from daemon.labelling.modules import order_modules

SUBJECT_REL = 0.15   # another body: distances differ by this fraction (1 SD) at least


def template_tolerance(ms: MarkerSet, noise_m: float = 0.003) -> np.ndarray:
    subject = np.maximum(ms.subject_sd_m, SUBJECT_REL * ms.mean_m)
    return 3.0 * np.sqrt(ms.sd_m ** 2 + subject ** 2 + 2 * noise_m ** 2) + 0.006


def _match_segment(P: np.ndarray, D: np.ndarray, members: list[int], ms: MarkerSet,
                   tol: np.ndarray, free: np.ndarray, limit: int = 64) -> list:
    """All assignments of `members` to free points whose pairwise distances fit, best
    first (backtracking over the gated pair table)."""
    m = len(members)
    mean = ms.mean_m[np.ix_(members, members)]
    tl = tol[np.ix_(members, members)]
    out: list[tuple[float, list[int]]] = []
    cand = np.nonzero(free)[0]

    def rec(chosen: list[int], cost: float) -> None:
        if len(out) > 4 * limit:
            return
        i = len(chosen)
        if i == m:
            out.append((cost, list(chosen)))
            return
        c = cand[~np.isin(cand, chosen)]
        if i:
            e = np.abs(D[np.ix_(chosen, c)] - mean[:i, i:i + 1]) / tl[:i, i:i + 1]
            ok = (e <= 1.0).all(0)
            c, e = c[ok], e[:, ok]
            costs = (e ** 2).sum(0)
        else:
            costs = np.zeros(len(c))
        for j, cc in zip(c, costs, strict=True):
            rec([*chosen, int(j)], cost + float(cc))

    rec([], 0.0)
    out.sort(key=lambda t: t[0])
    return out[:limit]


def initial_labels(P: np.ndarray, ms: MarkerSet, n_hypotheses: int = 24,
                   n_segments: int = 2, return_cost: bool = False):
    """Label one frame from the marker set alone: the steadiest multi-marker segment is
    matched by its distances (every fitting assignment is a hypothesis), the others grow
    from it by their distances to labelled markers, and the handedness checks (signed
    volumes) pick between a body and its mirror image. Returns a label per point (-1:
    ghost or unknown)."""
    P = np.asarray(P, float)
    k = len(P)
    lab = np.full(k, -1)
    if k < 3:
        return (lab, np.inf) if return_cost else lab
    D = np.linalg.norm(P[:, None] - P[None], axis=2)
    tol = template_tolerance(ms)
    order = sorted([s for s in ms.segments if len(s.markers) >= 3],
                   key=lambda s: (-len(s.markers), s.spread_m))
    best = None
    for seg in order[:n_segments]:
        hyps = _match_segment(P, D, seg.markers, ms, tol, np.ones(k, bool),
                              limit=n_hypotheses)
        for _, chosen in hyps:
            marker_point = np.full(ms.n, -1)
            marker_point[seg.markers] = chosen
            cost = _grow(P, D, ms, tol, marker_point)
            votes = chirality_votes(P, ms, marker_point)
            n_missing = int((marker_point < 0).sum())
            total = cost + 9.0 * n_missing - 3.0 * votes
            if best is None or total < best[0]:
                best = (total, marker_point)
    if best is None:
        return (lab, np.inf) if return_cost else lab
    mp = order_modules(P, ms, best[1].copy())
    got = mp >= 0
    lab[mp[got]] = np.nonzero(got)[0]
    return (lab, best[0]) if return_cost else lab


def _grow(P: np.ndarray, D: np.ndarray, ms: MarkerSet, tol: np.ndarray,
          marker_point: np.ndarray) -> float:
    """Label the rest one marker at a time: each step takes the unlabelled marker whose
    best point (by its distances to every labelled marker, weighted by how steady each
    distance is) stands out most clearly from its second best."""
    total = 0.0
    k = len(P)
    w_all = 1.0 / tol ** 2
    while True:
        todo = np.nonzero(marker_point < 0)[0]
        done = np.nonzero(marker_point >= 0)[0]
        if not len(todo) or not len(done):
            break
        used = np.zeros(k, bool)
        used[marker_point[done]] = True
        free = np.nonzero(~used)[0]
        if not len(free):
            break
        d = D[np.ix_(free, marker_point[done])]                       # (F, L)
        mu = ms.mean_m[np.ix_(todo, done)]                            # (T, L)
        w = w_all[np.ix_(todo, done)]
        e2 = np.minimum((d[None] - mu[:, None]) ** 2 * w[:, None] * 9.0, 16.0)  # (T, F, L)
        cost = (e2 * w[:, None]).sum(2) / w.sum(1)[:, None]          # weighted mean chi2/9
        if cost.shape[1] >= 2:
            part = np.partition(cost, 1, axis=1)
            best, second = part[:, 0], part[:, 1]
        else:
            best, second = cost[:, 0], np.full(len(todo), 16.0)
        ok = best < 9.0
        if not ok.any():
            break
        margin = np.where(ok, second - best, -np.inf)
        t = int(np.argmax(margin))
        marker_point[todo[t]] = free[int(np.argmin(cost[t]))]
        total += float(best[t])
    return total


def chirality_votes(P: np.ndarray, ms: MarkerSet, marker_point: np.ndarray) -> int:
    """Votes for this labelling's handedness matching the marker set's (+) or its mirror."""
    if not len(ms.chiral):
        return 0
    ok = (marker_point[ms.chiral] >= 0).all(1)
    if not ok.any():
        return 0
    x = np.full((ms.n, 3), np.nan)
    got = marker_point >= 0
    x[got] = P[marker_point[got]]
    v = signed_volume(x, ms.chiral[ok])
    return int((np.sign(v) == ms.chiral_sign[ok]).sum() - (np.sign(v) != ms.chiral_sign[ok]).sum())
