"""Scoring reconstructed 3D points against the simulator's truth: error, gross errors, recall
and ghosts.

One definition used by `calibkit triangulate --json`, the benchmarks, the tests and the demo,
so that every figure called "recall", "ghost" or "gross error" means the same thing everywhere.
A figure counts everything: the error RMS is over every point that stands for a marker, and
the points more than `tolerance_mm` off are counted beside it, never silently left out.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from scipy.spatial import cKDTree

from calibkit.core.observations import Observations, Truth


@dataclass(frozen=True)
class PointScore:
    points: int  # 3D points scored
    matched: int  # points that stand for a true marker (see score_points)
    ghosts: int  # points that stand for no marker
    ghost_fraction: float  # ghosts / points
    error_mm_rms: float  # over every matched point, gross errors included
    error_mm_median: float
    error_mm_max: float
    gross_errors: int  # matched points farther than tolerance_mm from their marker
    gross_fraction: float  # gross_errors / matched
    markers_seen_3: int  # (frame, marker) pairs seen by >= 3 cameras (needs blob labels)
    recall_3: float  # of those, the fraction some point stands for
    tolerance_mm: float
    matched_by: str  # "blobs": by the labels of each point's blobs; "distance": nearest marker

    def as_dict(self) -> dict:
        return asdict(self)


def nearest_truth(frame: np.ndarray, xyz: np.ndarray, truth: Truth) -> tuple[np.ndarray,
                                                                               np.ndarray]:
    """For each point, the nearest true marker of its frame: (marker id or -1, distance m)."""
    frames, markers, dense = _dense(truth)
    fi, known = _frame_index(frames, frame)
    best = np.full(len(frame), -1)
    dist = np.full(len(frame), np.inf)
    if np.any(known) and len(markers):
        d = np.linalg.norm(dense[fi[known]] - xyz[known][:, None, :], axis=2)
        d = np.where(np.isfinite(d), d, np.inf)
        j = np.argmin(d, axis=1)
        best[known] = markers[j]
        dist[known] = d[np.arange(len(j)), j]
    best[~np.isfinite(dist)] = -1
    return best, dist


def _dense(truth: Truth) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(frames, markers, positions (F, K, 3) with NaN where a marker has none)."""
    frames = np.unique(truth.frame)
    markers = np.unique(truth.marker)
    dense = np.full((len(frames), len(markers), 3), np.nan)
    dense[np.searchsorted(frames, truth.frame), np.searchsorted(markers, truth.marker)] = \
        truth.xyz
    return frames, markers, dense


def _frame_index(frames: np.ndarray, frame: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    fi = np.searchsorted(frames, frame)
    known = (fi < len(frames)) & (frames[np.minimum(fi, len(frames) - 1)] == frame)
    return np.minimum(fi, max(len(frames) - 1, 0)), known


def blob_marker(rows: np.ndarray, obs: Observations) -> np.ndarray:
    """The marker each point was made from: the true marker most of its blobs belong to,
    when at least two of them do (two rays fix a point); -1 otherwise (a ghost).

    rows: (P, C) the Observations row of each point's blob per camera, -1 where none."""
    rows = np.asarray(rows, dtype=np.int64).reshape(len(rows), -1)
    label = np.where(rows >= 0, obs.marker[np.maximum(rows, 0)], -1).astype(np.int64)
    label = np.sort(label, axis=1)
    # the longest run of one marker id along each sorted row
    best = np.full(len(rows), -1)
    best_n = np.zeros(len(rows), dtype=np.int64)
    run = np.ones(len(rows), dtype=np.int64)
    for j in range(label.shape[1]):  # a handful of cameras: a loop over columns, not points
        if j:
            same = label[:, j] == label[:, j - 1]
            run = np.where(same, run + 1, 1)
        better = (label[:, j] >= 0) & (run > best_n)
        best = np.where(better, label[:, j], best)
        best_n = np.where(better, run, best_n)
    return np.where(best_n >= 2, best, -1)


def stands_for(frame: np.ndarray, xyz: np.ndarray, truth: Truth,
               obs: Observations | None = None, rows: np.ndarray | None = None,
               tolerance_mm: float = 10.0) -> tuple[np.ndarray, np.ndarray, np.ndarray, str]:
    """The marker each point stands for: (marker id or -1, distance to it in metres (to the
    nearest marker for a ghost), matched or not, "blobs" or "distance"); see score_points."""
    frame = np.asarray(frame, dtype=np.int64).reshape(-1)
    xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    nearest, near_dist = nearest_truth(frame, xyz, truth)
    if rows is None or obs is None or obs.marker is None:
        matched = near_dist <= tolerance_mm / 1000.0
        return np.where(matched, nearest, -1), near_dist, matched, "distance"
    marker = blob_marker(rows, obs)
    frames, markers, dense = _dense(truth)
    fi, known = _frame_index(frames, frame)
    mi = np.minimum(np.searchsorted(markers, marker), max(len(markers) - 1, 0))
    has = (marker >= 0) & known & (len(markers) > 0)
    has[has] &= markers[mi[has]] == marker[has]
    dist = near_dist.copy()
    dist[has] = np.linalg.norm(dense[fi[has], mi[has]] - xyz[has], axis=1)
    matched = has & np.isfinite(dist)
    dist[has & ~matched] = near_dist[has & ~matched]
    return np.where(matched, marker, -1), dist, matched, "blobs"


def score_points(frame: np.ndarray, xyz: np.ndarray, truth: Truth,
                 obs: Observations | None = None, tolerance_mm: float = 10.0,
                 rows: np.ndarray | None = None) -> PointScore:
    """Score points (frame (P,), xyz (P, 3)) against the truth.

    Which marker a point stands for: with `rows` (each point's blobs, as FramePoints.rows)
    and observations carrying the simulator's blob labels, the marker most of its blobs
    belong to (at least two); a point made of no marker's blobs is a ghost, and one made of
    a marker's blobs but more than `tolerance_mm` from it is a gross error: counted beside
    the error RMS, which is over every matched point. Without them, the nearest marker within
    `tolerance_mm`, so that gross errors cannot be told from ghosts and count as ghosts.

    With labelled observations, recall is measured over the markers that at least three
    cameras saw (those a correspondence method must find): the fraction some point stands for.
    """
    frame = np.asarray(frame, dtype=np.int64).reshape(-1)
    marker, dist, matched, by = stands_for(frame, xyz, truth, obs, rows, tolerance_mm)
    labelled = obs is not None and obs.marker is not None
    err_mm = dist[matched] * 1000.0
    seen3, recall = 0, float("nan")
    if labelled:
        real = obs.marker >= 0
        key_obs = obs.frame[real] * (1 << 20) + obs.marker[real]
        # count distinct cameras per (frame, marker)
        pair = np.unique(key_obs * 64 + obs.camera[real])
        keys, counts = np.unique(pair // 64, return_counts=True)
        need = keys[counts >= 3]
        seen3 = int(len(need))
        found = np.unique(frame[matched] * (1 << 20) + marker[matched])
        recall = float(np.isin(need, found).mean()) if seen3 else float("nan")
    n, m = len(frame), int(matched.sum())
    gross = int(np.sum(err_mm > tolerance_mm))
    return PointScore(
        points=n, matched=m, ghosts=n - m, ghost_fraction=float((n - m) / n) if n else 0.0,
        error_mm_rms=float(np.sqrt(np.mean(err_mm**2))) if m else float("nan"),
        error_mm_median=float(np.median(err_mm)) if m else float("nan"),
        error_mm_max=float(np.max(err_mm)) if m else float("nan"),
        gross_errors=gross, gross_fraction=float(gross / m) if m else 0.0,
        markers_seen_3=seen3, recall_3=recall, tolerance_mm=tolerance_mm, matched_by=by)


def match_to_truth(uv: np.ndarray, truth_uv: np.ndarray,
                   max_dist_px: float = 1.5) -> tuple[np.ndarray, np.ndarray]:
    """Pair detected centroids with true centres: mutual nearest neighbours within max_dist_px.

    Returns (detected index, true index) arrays of the pairs; the simulator's tests,
    benchmarks and `calibkit detect --sim` score recall, false blobs and centroid error
    from them.
    """
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    truth_uv = np.asarray(truth_uv, dtype=np.float64).reshape(-1, 2)
    if len(uv) == 0 or len(truth_uv) == 0:
        z = np.zeros(0, dtype=np.int64)
        return z, z
    d_t, to_truth = cKDTree(truth_uv).query(uv)
    _, to_det = cKDTree(uv).query(truth_uv)
    det = np.flatnonzero((to_det[to_truth] == np.arange(len(uv))) & (d_t <= max_dist_px))
    return det, to_truth[det]
