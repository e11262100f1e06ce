"""Starting a take's labels from the marker set alone, on a window of frames.

A single frame does not say which point is which on a body the set was not learned on;
a second of motion does (which pairs keep their distance, how far apart they stay).
The window where the most points are seen is chosen, its points are linked into tracks
(the point nearest each track's constant-velocity prediction, one assignment per frame;
ghosts do not last and fall out; pieces of one marker lost and found again are joined),
and the tracks are assigned to markers all at once (daemon/labelling/assign.py).
The window's labelled frames then start the tracker as labelled start frames would
(the tracker learns this body's own distances from them).
"""

from __future__ import annotations

import numpy as np

from calibkit.core.assignment import linear_sum_assignment
from daemon.labelling.assign import pair_stats
from daemon.labelling.markerset import MarkerSet
from daemon.labelling.unfit import assign_pruned

WINDOW = 120             # frames in the start window
GATE_M = 0.05
UNFIT_SEEN = 0.95        # a track fitting no marker, seen this much of the window: a marker


def link_window(frames: list[np.ndarray], gate_m: float = GATE_M, min_seen: float = 0.3
                ) -> tuple[np.ndarray, np.ndarray]:
    """Points of consecutive frames linked into tracks: (T, W, 3) positions (NaN where a
    track has no point) and (T, W) the point's row in its frame (-1). A track follows the
    point nearest its constant-velocity prediction (one assignment per frame, the gate
    widening while it is unseen); points left over start tracks; tracks seen in fewer
    than `min_seen` of the frames (ghosts, mostly) are dropped."""
    W = len(frames)
    pos = np.zeros((0, 3))
    vel = np.zeros((0, 3))
    miss = np.zeros(0, int)
    rows = np.full((0, W), -1)
    for w, P in enumerate(frames):
        P = np.asarray(P, float).reshape(-1, 3)
        taken = np.zeros(len(P), bool)
        hit = np.zeros(len(pos), bool)
        live = np.nonzero(miss < 4)[0]
        if len(live) and len(P):
            q = pos[live] + vel[live] * (miss[live] + 1)[:, None]
            d = np.linalg.norm(q[:, None] - P[None], axis=2)
            gate = gate_m * (1 + miss[live])
            d = np.where(d > gate[:, None], 1e6, d)
            r, c = linear_sum_assignment(d)
            ok = d[r, c] < 1e6
            t, b = live[r[ok]], c[ok]
            vel[t] = (P[b] - pos[t]) / (miss[t] + 1)[:, None]
            pos[t] = P[b]
            rows[t, w] = b
            taken[b] = True
            hit[t] = True
        miss = np.where(hit, 0, miss + 1)
        new = np.nonzero(~taken)[0]
        k = len(new)
        if k:
            pos = np.concatenate([pos, P[new]])
            vel = np.concatenate([vel, np.zeros((k, 3))])
            miss = np.concatenate([miss, np.zeros(k, int)])
            add = np.full((k, W), -1)
            add[:, w] = new
            rows = np.concatenate([rows, add])
    idx = rows
    keep = (idx >= 0).sum(1) >= max(2, min_seen * W)
    idx = idx[keep]
    X = np.full(idx.shape + (3,), np.nan)
    for w, P in enumerate(frames):
        got = idx[:, w] >= 0
        X[got, w] = np.asarray(P, float).reshape(-1, 3)[idx[got, w]]
    return X, idx


def join_fragments(X: np.ndarray, idx: np.ndarray, within_m: float = 0.015,
                   near_m: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """Tracks that are one marker lost for a while and found again, joined: two tracks
    never seen in the same frame whose distances to the tracks near them (within
    `near_m`) agree within `within_m` (median), closest first."""
    while True:
        T = len(X)
        if T < 3:
            return X, idx
        seen = idx >= 0
        D, _ = pair_stats(X)
        together = (seen[:, None] & seen[None]).any(2)
        best = None
        for a in range(T):
            for b in range(a + 1, T):
                if together[a, b]:
                    continue
                c = np.isfinite(D[a]) & np.isfinite(D[b]) & (np.minimum(D[a], D[b]) < near_m)
                c[[a, b]] = False
                if c.sum() < 3:
                    continue
                e = float(np.median(np.abs(D[a, c] - D[b, c])))
                if e < within_m and (best is None or e < best[0]):
                    best = (e, a, b)
        if best is None:
            return X, idx
        _, a, b = best
        take = seen[b]
        X[a, take] = X[b, take]
        idx[a, take] = idx[b, take]
        X = np.delete(X, b, axis=0)
        idx = np.delete(idx, b, axis=0)


def choose_window(counts: np.ndarray, n: int, width: int = WINDOW, search: int = 600,
                  step: int = 10) -> int:
    """The first frame of the window (within the first `search` frames) where most
    markers are seen: the most points (counted up to the set's size) over the window."""
    c = np.minimum(counts, n).astype(float)
    last = max(0, min(len(c) - width, search))
    starts = np.arange(0, last + 1, step)
    cs = np.concatenate([[0.0], np.cumsum(c)])
    tot = cs[np.minimum(starts + width, len(c))] - cs[starts]
    return int(starts[int(np.argmax(tot))])


def window_start(per_frame: list[np.ndarray], ms: MarkerSet, width: int = WINDOW,
                 noise_m: float = 0.003, merge_m: float = 0.0, unfit: list | None = None
                 ) -> tuple[int, list[np.ndarray], np.ndarray]:
    """Label a window of frames from the marker set alone. Returns its first frame index,
    each window frame's labels (a marker per point, -1 none; a point within `merge_m`
    of a labelled one is the same marker seen twice and takes its label) and the
    window's labelled positions (W, n, 3), NaN where unlabelled. `unfit`, if given,
    gets the positions (W, 3) of the window's tracks that fit no marker of the set
    (left out by the assignment, daemon/labelling/unfit.py) and are seen in UNFIT_SEEN
    of it: markers the set lacks (a marker of the set left out, seen less, is left to
    the tracker to find)."""
    counts = np.array([len(p) for p in per_frame])
    w0 = choose_window(counts, ms.n, width)
    frames = per_frame[w0:w0 + width]
    X, idx = join_fragments(*link_window(frames, min_seen=0.1))
    keep = (idx >= 0).sum(1) >= 0.3 * len(frames)     # ghosts (and scraps) fall out
    X, idx = X[keep], idx[keep]
    left: list[int] = []
    lab, _ = assign_pruned(X, ms, noise_m=noise_m, left=left) if len(X) >= 3 else \
        (np.full(len(X), -1), 0.0)
    if unfit is not None:       # (a marker's track seen throughout: no scrap, no ghost)
        unfit.extend(X[t] for t in left
                     if lab[t] < 0 and (idx[t] >= 0).sum() >= UNFIT_SEEN * len(frames))
    W = len(frames)
    labels = [np.full(len(p), -1) for p in frames]
    xyz = np.full((W, ms.n, 3), np.nan)
    for t in np.nonzero(lab >= 0)[0]:
        for w in np.nonzero(idx[t] >= 0)[0]:
            labels[w][idx[t, w]] = lab[t]
        xyz[:, lab[t]] = X[t]
    if merge_m > 0:
        for w, P in enumerate(frames):
            m = labels[w]
            if (m >= 0).all() or not (m >= 0).any():
                continue
            free, got = np.nonzero(m < 0)[0], np.nonzero(m >= 0)[0]
            d = np.linalg.norm(P[free, None] - P[None, got], axis=2)
            near = d.min(1) < merge_m
            m[free[near]] = m[got[d[near].argmin(1)]]
    return w0, labels, xyz
