"""Scoring reconstructed 3D points against the simulator's truth: error, recall and ghosts.

One definition used by `calibkit triangulate --json`, the benchmarks, the tests and the demo,
so that every figure called "recall" or "ghost" means the same thing everywhere.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from scipy.spatial import cKDTree

from calibkit.observations import Observations, Truth


@dataclass(frozen=True)
class PointScore:
    points: int  # 3D points scored
    ghosts: int  # points farther than the tolerance from every true marker of their frame
    ghost_fraction: float
    error_mm_rms: float  # over the points that are not ghosts
    error_mm_median: float
    markers_seen_3: int  # (frame, marker) pairs seen by >= 3 cameras (needs blob labels)
    recall_3: float  # of those, the fraction with a reconstructed point within tolerance
    tolerance_mm: float

    def as_dict(self) -> dict:
        return asdict(self)


def nearest_truth(frame: np.ndarray, xyz: np.ndarray, truth: Truth) -> tuple[np.ndarray,
                                                                               np.ndarray]:
    """For each point, the nearest true marker of its frame: (marker id or -1, distance m)."""
    frames = np.unique(truth.frame)
    markers = np.unique(truth.marker)
    dense = np.full((len(frames), len(markers), 3), np.nan)
    dense[np.searchsorted(frames, truth.frame), np.searchsorted(markers, truth.marker)] = \
        truth.xyz
    fi = np.searchsorted(frames, frame)
    known = (fi < len(frames)) & (frames[np.minimum(fi, len(frames) - 1)] == frame)
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


def score_points(frame: np.ndarray, xyz: np.ndarray, truth: Truth,
                 obs: Observations | None = None, tolerance_mm: float = 10.0) -> PointScore:
    """Score points (frame (P,), xyz (P, 3)) against the truth.

    With observations carrying the simulator's blob labels, recall is measured over the
    markers that at least three cameras saw: those a correspondence method must find.
    """
    frame = np.asarray(frame, dtype=np.int64)
    xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    marker, dist = nearest_truth(frame, xyz, truth)
    tol = tolerance_mm / 1000.0
    good = dist <= tol
    err_mm = dist[good] * 1000.0
    seen3, recall = 0, float("nan")
    if obs is not None and obs.marker is not None:
        labelled = obs.marker >= 0
        key_obs = obs.frame[labelled] * (1 << 20) + obs.marker[labelled]
        # count distinct cameras per (frame, marker)
        pair = np.unique(key_obs * 64 + obs.camera[labelled])
        keys, counts = np.unique(pair // 64, return_counts=True)
        need = keys[counts >= 3]
        seen3 = int(len(need))
        found = np.unique(frame[good] * (1 << 20) + marker[good])
        recall = float(np.isin(need, found).mean()) if seen3 else float("nan")
    n = len(frame)
    return PointScore(
        points=n, ghosts=int(n - good.sum()),
        ghost_fraction=float((n - good.sum()) / n) if n else 0.0,
        error_mm_rms=float(np.sqrt(np.mean(err_mm**2))) if len(err_mm) else float("nan"),
        error_mm_median=float(np.median(err_mm)) if len(err_mm) else float("nan"),
        markers_seen_3=seen3, recall_3=recall, tolerance_mm=tolerance_mm)


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
