"""Defining a rigid body from what the tracker saw of it over a few frames.

Why several frames: one frame's tracked points carry that frame's noise, may miss a marker
hidden from all but one camera, and may hold a ghost (a stray blob that happened to
triangulate); a definition is used for the whole session, so it is worth a second of
capture. The frames are put on top of each other by the tracks' identities (a rigid fit
on the tracks they share with the fullest frame, so the object may move a little), the
points are clustered, and a marker is a cluster seen in most frames, at its median.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence

import numpy as np

from calibkit.core.errors import UserError
from daemon.tracking.rigid import kabsch_batch


def body_from_snapshots(snapshots: Sequence[tuple[np.ndarray, np.ndarray]],
                        cluster_m: float = 0.004, min_share: float = 0.5,
                        max_spread_m: float = 0.004) -> np.ndarray:
    """Markers (k, 3) of one object in a new body frame (origin at their centroid, the
    world's axes as they were in the fullest frame) from frames of tracked points, each
    (track ids (n,), positions (n, 3)) of that object alone.

    cluster_m: points of one marker from different frames lie this close after the frames
    are aligned (far below any two markers' distance); min_share: a marker is a cluster
    found in at least this share of the frames (ghosts and duplicates are not);
    max_spread_m: a cluster whose points lie farther than this from its centre (the median
    distance: a stray point joined to it does not count) means the points did not hold
    still relative to each other (a marker wobbling, two tracks swapping): an error.
    """
    frames = [(np.asarray(i, dtype=np.int64).reshape(-1),
               np.asarray(x, dtype=np.float64).reshape(-1, 3)) for i, x in snapshots]
    frames = [(i, x) for i, x in frames if len(i)]
    if not frames:
        raise UserError("the daemon tracked no markers during the capture")
    ids, counts = np.unique(np.concatenate([i for i, _ in frames]), return_counts=True)
    steady = ids[counts >= min_share * len(frames)]
    ref = max(range(len(frames)), key=lambda k: np.isin(frames[k][0], steady).sum())
    ref_ids, ref_xyz = frames[ref]
    # twice: the second pass aligns every frame to the first pass's averaged points
    # instead of one frame's noisy ones
    for _ in range(2):
        pts, raw, frame_of, group, keep = _cluster(frames, ref_ids, ref_xyz, cluster_m,
                                                   min_share)
        centre = {int(g): np.median(pts[group == g], axis=0) for g in keep}
        ref_group = group[frame_of == ref]
        ref_xyz = np.array([centre.get(int(g), p) for g, p in
                            zip(ref_group, pts[frame_of == ref], strict=True)])
    markers = np.array([centre[int(g)] for g in keep]).reshape(-1, 3)
    spread = np.array([np.median(np.linalg.norm(pts[group == g] - m, axis=1))
                       for g, m in zip(keep, markers, strict=True)])
    if len(spread) and spread.max() > max_spread_m:
        raise UserError(f"a marker's position varied by {spread.max() * 1000:.1f} mm "
                        "(median) during the capture; hold the body still and alone in the "
                        "volume")
    markers = _in_mean_pose(markers, keep, raw, frame_of, group)
    return markers - markers.mean(axis=0) if len(markers) else markers


def learn_body(track: Callable, frame_sets: Iterable, skip_frames: int = 5) -> np.ndarray:
    """A body's markers (body frame, as body_from_snapshots) from frame sets of it held
    still and alone: `track(frame_set)` is the daemon's tracker (its TrackFrame), and the
    points it sees in each frame after the first `skip_frames` (while it finds them) are
    the snapshots, as `mocapd rigid-body add --from-live` takes them from a running daemon.
    """
    snapshots = []
    for k, fs in enumerate(frame_sets):
        tr = track(fs)
        if k >= skip_frames:
            snapshots.append((tr.ids[tr.seen], tr.xyz[tr.seen]))
    return body_from_snapshots(snapshots)


def bodies_toml(bodies: Sequence[tuple[str, int, np.ndarray]]) -> str:
    """[[rigid_body]] tables (name, id, markers in metres) as a configuration holds them."""
    # deferred on purpose: loads tomli_w only where used
    import tomli_w

    return tomli_w.dumps({"rigid_body": [{"name": name, "id": int(body_id),
                                          "markers": np.round(m, 6).tolist()}
                                         for name, body_id, m in bodies]})


def _in_mean_pose(markers, keep, raw, frame_of, group):
    """The averaged shape placed at the object's mean pose over the frames (not the one
    frame it was aligned to, whose noise would tilt the body's axes)."""
    slot = np.full(group.max() + 1, -1)
    slot[keep] = np.arange(len(keep))
    Rs, ts = [], []
    for k in np.unique(frame_of):
        rows = np.flatnonzero((frame_of == k) & (slot[group] >= 0))
        if len(rows) < 3:
            continue
        R, t = kabsch_batch(markers[slot[group[rows]]][None], raw[rows][None],
                            np.ones((1, len(rows))))
        Rs.append(R[0])
        ts.append(t[0])
    if not Rs:
        return markers
    U, _, Vt = np.linalg.svd(np.mean(Rs, axis=0))
    R = U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt
    return markers @ R.T + np.mean(ts, axis=0)


def _cluster(frames, ref_ids, ref_xyz, cluster_m, min_share):
    """Every frame moved onto the reference points (a rigid fit on the track ids it shares
    with them), the points pooled and clustered: (points moved, as they were, their frame,
    their cluster, the clusters seen in at least min_share of the frames)."""
    # deferred on purpose: loads SciPy's sparse graphs, SciPy's spatial only where used
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    aligned, raw, used = [], [], []
    for k, (i, x) in enumerate(frames):
        common, a, b = np.intersect1d(i, ref_ids, return_indices=True)
        if len(common) < 3:
            continue
        R, t = kabsch_batch(x[a][None], ref_xyz[b][None], np.ones((1, len(common))))
        aligned.append(x @ R[0].T + t[0])
        raw.append(x)
        used.append(np.full(len(x), k))
    if len(aligned) < 2:
        raise UserError("no two frames of the capture share three markers; hold the body "
                        "still in view of the cameras")
    pts, frame_of = np.concatenate(aligned), np.concatenate(used)
    pairs = cKDTree(pts).query_pairs(cluster_m, output_type="ndarray")
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])),
                       shape=(len(pts), len(pts)))
    n_groups, group = connected_components(graph, directed=False)
    # frames each cluster was seen in (a frame counted once per cluster)
    seen = np.unique(group * len(frames) + frame_of)
    share = np.bincount(seen // len(frames), minlength=n_groups) / len(aligned)
    return pts, np.concatenate(raw), frame_of, group, np.flatnonzero(share >= min_share)
