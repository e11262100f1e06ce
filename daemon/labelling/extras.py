"""Markers the set lacks, found in labelled start frames and tracked as markers of their own.

A labelled start says more than which points are which markers: a point that lasts
through the start frames and is labelled nowhere in them is a marker the set does not
have (another lab's addition, a marker stuck on for a prop). Left to the tracker as an
unlabelled point, it is the nearest candidate when the set's marker beside it is hidden,
and takes that marker's name (on a body with three such markers, one took CLAV's name in
251 frames and another LFHD's in 139). So each such point is added to the marker set as a
marker of its own for this take (`with_extras`): named, tracked and re-identified like
the others from the start's own distances, so that its point is held and no marker of
the set can take it. Its spreads are borrowed from the set's marker nearest to it (it
rides the same segment, a few centimetres away), which also puts it into that marker's
rigid module. Output drops these markers: their points stay unlabelled, unless
verification, weighing the evidence, renames one as a marker of the set.
"""

from __future__ import annotations

import warnings

import numpy as np

from daemon.labelling.markerset import MarkerSet
from daemon.labelling.single import template_tolerance
from daemon.labelling.start import link_window

MIN_SEEN = 0.5        # a point in at least half the start frames is a marker, not a ghost
STEADY_M = 0.01       # ... and it keeps its distance to its nearest marker within this (SD)
ABSENT_SD = 2.0       # a track this close (SD) to where a marker the start lacks would be


def unlabelled_tracks(per_frame: list[np.ndarray], xyz: np.ndarray, within_m: float,
                      ms: MarkerSet) -> np.ndarray:
    """The points of labelled start frames (per_frame[f], positions xyz (W, n, 3) of the
    set's markers) that no label holds (none within `within_m` of them), linked over the
    frames: tracks (E, W, 3) seen in MIN_SEEN of the frames that keep their distance to
    the nearest labelled marker steady (a marker riding a segment; ghosts do not last),
    and that no marker of the set `ms` the start leaves unlabelled could be."""
    W = len(xyz)
    free = []
    for f in range(W):
        P = np.asarray(per_frame[f], float).reshape(-1, 3)
        L = xyz[f][np.isfinite(xyz[f]).all(1)]
        if len(P) and len(L):
            d = np.linalg.norm(P[:, None] - L[None], axis=2).min(1)
            P = P[d > within_m]
        free.append(P)
    if W < 2 or sum(len(p) for p in free) < 2:
        return np.zeros((0, W, 3))
    X, _ = link_window(free, min_seen=MIN_SEEN)
    if not len(X):
        return X
    keep = []
    for e in range(len(X)):
        d = np.linalg.norm(X[e][:, None] - xyz, axis=2)                  # (W, n)
        with np.errstate(all="ignore"):
            near = np.nanargmin(np.where(np.isfinite(d), d, np.inf).mean(0))
        col = d[:, near]
        col = col[np.isfinite(col)]
        keep.append(len(col) >= 2 and float(np.std(col)) < STEADY_M
                    and not fits_absent(X[e], xyz, ms))
    return X[np.array(keep, bool)]


def fits_absent(track: np.ndarray, xyz: np.ndarray, ms: MarkerSet, within: float = ABSENT_SD,
                k: int = 6) -> bool:
    """Whether a track (W, 3) of the start frames could be a marker of the set that the
    start leaves unlabelled throughout (xyz (W, n, 3)): its distances to that marker's
    `k` steadiest labelled neighbours within `within` SD of the set's (scaled to this
    body; one SD for another subject, `template_tolerance` / 3) at the median. A start
    that did not label a marker whose point is there says nothing about that point."""
    seen = np.isfinite(xyz).all(2).any(0)
    absent = np.nonzero(~seen)[0]
    if not len(absent) or seen.sum() < 3:
        return False
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        d = np.nanmean(np.linalg.norm(xyz[:, :, None] - xyz[:, None], axis=3), axis=0)
        scale = float(np.nanmedian(d[np.ix_(seen, seen)] / ms.mean_m[np.ix_(seen, seen)]))
        to = np.nanmean(np.linalg.norm(track[:, None] - xyz, axis=2), axis=0)       # (n,)
    sd = template_tolerance(ms) / 3.0
    for j in absent:
        nb = np.argsort(np.where(seen & np.isfinite(to), ms.sd_m[j], np.inf))[:k]
        nb = nb[seen[nb] & np.isfinite(to[nb])]
        if len(nb) >= 3 and np.median(np.abs(to[nb] - scale * ms.mean_m[j, nb])
                                      / sd[j, nb]) <= within:
            return True
    return False


def with_extras(ms: MarkerSet, xyz: np.ndarray, extra: np.ndarray) -> MarkerSet:
    """The marker set with the tracks `extra` (E, W, 3) of labelled frames xyz (W, n, 3)
    as markers of its own (named after the set's marker nearest each, e.g. "CLAV+1"):
    their mean distances from these frames, their spreads (and between subjects) those
    of that nearest marker, held to it as steadily as it is held to its steadiest
    neighbour. The set's segments, handedness and swap witnesses are kept as they are."""
    E = len(extra)
    if not E:
        return ms
    n = ms.n
    allx = np.concatenate([xyz, extra.transpose(1, 0, 2)], axis=1)      # (W, n + E, 3)
    d = np.linalg.norm(allx[:, :, None] - allx[:, None], axis=3)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)   # pairs never seen together
        mean = np.nanmean(d, axis=0)
    near = np.nanargmin(np.where(np.isfinite(mean[n:, :n]), mean[n:, :n], np.inf), axis=1)
    src = np.concatenate([np.arange(n), near])                 # whose spreads each borrows
    sd = ms.sd_m[np.ix_(src, src)].copy()
    sub = ms.subject_sd_m[np.ix_(src, src)].copy()
    off = ms.sd_m + np.diag(np.full(n, np.inf))
    for e in range(E):
        steady = float(off[near[e]].min())
        k = n + e
        sd[k, near[e]] = sd[near[e], k] = steady
        sub[k, near[e]] = sub[near[e], k] = 0.0
        same = near == near[e]                  # two extras by one marker: as steady
        sd[k, n:][same] = sd[n:, k][same] = steady
    np.fill_diagonal(sd, ms.sd_m[0, 0] if n else 0.0)
    np.fill_diagonal(sub, 0.0)
    set_mean = ms.mean_m[np.ix_(src, src)]
    mean = np.where(np.isfinite(mean), mean, set_mean)
    mean[:n, :n] = ms.mean_m
    np.fill_diagonal(mean, 0.0)
    names = [f"{ms.labels[m]}+{e + 1}" for e, m in enumerate(near)]
    return MarkerSet(list(ms.labels) + names, mean, sd, ms.segments, ms.chiral,
                     ms.chiral_sign, ms.name, sub, ms.pair_quads, ms.pair_sign,
                     ms.pair_volume)
