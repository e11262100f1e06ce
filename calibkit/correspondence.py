"""Which blobs in different cameras are the same marker: epipolar matching of unlabelled blobs.

The seed thesis's method, vectorised per camera pair: every blob's candidates are the blobs
near its epipolar line in the other cameras; each candidate's ray meets the blob's ray at a
point along it; those points are clustered by depth, and a cluster seen by >= 3 cameras is
a marker. Clusters are verified by triangulation (their rays must really meet), then
accepted best first with each blob used at most once. Two-camera matches are added only
where the pairing is unique both ways, because two rays always "meet" somewhere on the
epipolar line and a ghost is otherwise indistinguishable from a marker.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calibkit.camera import Rig
from calibkit.geometry import RigArrays, Triangulation, triangulate
from calibkit.observations import Observations


@dataclass(frozen=True)
class CorrespondenceConfig:
    epipolar_px: float = 2.0  # how far a candidate may lie from the epipolar line
    cluster_m: float = 0.01  # gap along the ray that separates two clusters (+1 % of depth)
    max_reproj_px: float = 1.5  # a cluster whose rays do not meet this well is a ghost
    min_cameras: int = 3
    two_camera: bool = True  # also accept unambiguous pairs


@dataclass(eq=False)
class Matches:
    """Markers found in one frame: positions, quality, and the blobs each was made from."""

    xyz: np.ndarray  # (P, 3)
    reproj_px: np.ndarray  # (P,)
    ray_dist_m: np.ndarray  # (P,)
    n_cameras: np.ndarray  # (P,)
    blobs: np.ndarray  # (P, C) index into the frame's blob arrays, -1 where not seen

    def __len__(self) -> int:
        return len(self.xyz)


def _essentials(arrays: RigArrays) -> np.ndarray:
    """E[i, j] maps normalised points of camera i to epipolar lines of camera j."""
    R, t = arrays.R, arrays.t
    R_ij = np.einsum("jab,icb->ijac", R, R)  # R_j R_i^T
    t_ij = t[None, :, :] - np.einsum("ijab,ib->ija", R_ij, t)
    tx = np.zeros(t_ij.shape + (3,))
    tx[..., 0, 1], tx[..., 0, 2] = -t_ij[..., 2], t_ij[..., 1]
    tx[..., 1, 0], tx[..., 1, 2] = t_ij[..., 2], -t_ij[..., 0]
    tx[..., 2, 0], tx[..., 2, 1] = -t_ij[..., 1], t_ij[..., 0]
    return tx @ R_ij


_E_CACHE: dict[int, tuple[RigArrays, np.ndarray]] = {}


def _pairs(arrays: RigArrays, camera: np.ndarray, n: np.ndarray, origins: np.ndarray,
           dirs: np.ndarray, tol_px: float):
    """Candidate blob pairs (a, b) in different cameras, their ray meeting points and depths."""
    key = id(arrays)
    cached = _E_CACHE.get(key)
    if cached is None or cached[0] is not arrays:
        cached = (arrays, _essentials(arrays))
        _E_CACHE[key] = cached
    E = cached[1]
    cams = np.unique(camera)
    by_cam = {int(c): np.flatnonzero(camera == c) for c in cams}
    homog = np.concatenate([n, np.ones((len(n), 1))], axis=1)
    out_a, out_b = [], []
    for ii, ci in enumerate(cams):
        a = by_cam[int(ci)]
        for cj in cams[ii + 1:]:
            b = by_cam[int(cj)]
            lines_j = homog[a] @ E[ci, cj].T  # (A, 3) lines in camera j
            lines_i = homog[b] @ E[ci, cj]  # (B, 3) lines in camera i
            num = np.abs(lines_j @ homog[b].T)  # (A, B) = |x_b^T E x_a|
            dj = num / np.hypot(lines_j[:, 0], lines_j[:, 1])[:, None] * arrays.fx[cj]
            di = num / np.hypot(lines_i[:, 0], lines_i[:, 1])[None, :] * arrays.fx[ci]
            ia, ib = np.nonzero(np.maximum(di, dj) < tol_px)
            out_a.append(a[ia])
            out_b.append(b[ib])
    if not out_a:
        empty = np.zeros(0, dtype=np.int64)
        return empty, empty, np.zeros((0, 3)), np.zeros(0), np.zeros(0)
    pa, pb = np.concatenate(out_a), np.concatenate(out_b)
    # closest points of the two rays: o_a + s d_a and o_b + u d_b
    da, db = dirs[pa], dirs[pb]
    w = origins[pa] - origins[pb]
    b_ = np.sum(da * db, axis=1)
    d_ = np.sum(da * w, axis=1)
    e_ = np.sum(db * w, axis=1)
    denom = np.maximum(1.0 - b_ * b_, 1e-12)
    s = (b_ * e_ - d_) / denom
    u = (e_ - b_ * d_) / denom
    point = 0.5 * (origins[pa] + s[:, None] * da + origins[pb] + u[:, None] * db)
    front = (s > 0) & (u > 0)
    return pa[front], pb[front], point[front], s[front], u[front]


def _clusters(ref: np.ndarray, other: np.ndarray, depth: np.ndarray, camera: np.ndarray,
              cfg: CorrespondenceConfig):
    """Cluster each reference blob's candidates by depth along its ray.

    Returns (cluster id per kept candidate, reference blob per cluster, kept candidates,
    cameras per cluster) with at most one candidate per camera in a cluster (the one
    nearest the cluster's mean depth).
    """
    order = np.lexsort((depth, ref))
    ref, other, depth = ref[order], other[order], depth[order]
    gap = np.diff(depth) > cfg.cluster_m + 0.01 * depth[1:]
    new = np.r_[True, (ref[1:] != ref[:-1]) | gap]
    cid = np.cumsum(new) - 1
    n_clusters = int(cid[-1]) + 1 if len(cid) else 0
    mean = np.bincount(cid, weights=depth, minlength=n_clusters) / np.maximum(
        np.bincount(cid, minlength=n_clusters), 1)
    dev = np.abs(depth - mean[cid])
    cam = camera[other]
    keep_order = np.lexsort((dev, cam, cid))
    first = np.r_[True, (cid[keep_order][1:] != cid[keep_order][:-1])
                  | (cam[keep_order][1:] != cam[keep_order][:-1])]
    kept = keep_order[first]
    cid_k, other_k = cid[kept], other[kept]
    cluster_ref = ref[new]
    n_cams = np.bincount(cid_k, minlength=n_clusters) + 1
    return cid_k, cluster_ref, other_k, n_cams


def _resolve(member_cluster: np.ndarray, member_blob: np.ndarray, rank: np.ndarray,
             n_blobs: int) -> np.ndarray:
    """Accept clusters best-rank first so that no blob is used twice; vectorised in rounds:
    a cluster is accepted when it is the best remaining cluster of every blob it uses."""
    n_clusters = len(rank)
    alive = np.ones(n_clusters, dtype=bool)
    accepted = np.zeros(n_clusters, dtype=bool)
    used = np.zeros(n_blobs, dtype=bool)
    size = np.bincount(member_cluster, minlength=n_clusters)
    while True:
        live = alive[member_cluster]
        if not np.any(live):
            break
        best = np.full(n_blobs, np.iinfo(np.int64).max)
        np.minimum.at(best, member_blob[live], rank[member_cluster[live]])
        is_best = live & (best[member_blob] == rank[member_cluster])
        wins = (np.bincount(member_cluster[is_best], minlength=n_clusters) == size) & alive
        if not np.any(wins):
            break
        accepted |= wins
        used[member_blob[wins[member_cluster]]] = True
        touched = np.bincount(member_cluster, weights=used[member_blob],
                              minlength=n_clusters) > 0
        alive &= ~touched
    return accepted


def _prune(rig: Rig, arrays: RigArrays, table: np.ndarray, camera: np.ndarray, uv: np.ndarray,
           cfg: CorrespondenceConfig, rounds: int = 2) -> tuple[np.ndarray, Triangulation]:
    """Triangulate candidate markers (rows of `table`) and drop, per round, each one's worst
    observation if it misses by more than max_reproj_px: one wrong blob among eight cameras
    hides in a point's RMS but not in its own residual."""
    for _ in range(rounds + 1):
        point, cam = np.nonzero(table >= 0)
        blob = table[point, cam]
        tri = triangulate(rig, point, cam, uv[blob], iterations=1, n_points=len(table),
                          ray_distance=False)
        proj, _ = arrays.project(cam, np.nan_to_num(tri.xyz[point]))
        resid = np.linalg.norm(proj - uv[blob], axis=1)
        worst = np.full(len(table), -1.0)
        np.maximum.at(worst, point, resid)
        drop = (resid == worst[point]) & (resid > cfg.max_reproj_px)
        if not np.any(drop):
            break
        table = table.copy()
        table[point[drop], cam[drop]] = -1
    return table, tri


def _cluster_pass(rig: Rig, arrays: RigArrays, camera: np.ndarray, uv: np.ndarray,
                  n: np.ndarray, origins: np.ndarray, dirs: np.ndarray, available: np.ndarray,
                  cfg: CorrespondenceConfig) -> tuple[np.ndarray, tuple]:
    """Markers seen by >= min_cameras among the `available` blobs: (P, C) blob table, and the
    candidate pairs found (for the two-camera step)."""
    n_cams_rig = len(rig)
    sub = np.flatnonzero(available)
    pa, pb, _, s, u = _pairs(arrays, camera[sub], n[sub], origins[sub], dirs[sub],
                             cfg.epipolar_px)
    pa, pb = sub[pa], sub[pb]
    none = np.zeros((0, n_cams_rig), dtype=np.int64)
    if not len(pa) or cfg.min_cameras > n_cams_rig:
        return none, (pa, pb)
    ref = np.concatenate([pa, pb])
    other = np.concatenate([pb, pa])
    depth = np.concatenate([s, u])
    cid, cluster_ref, other_k, n_cl = _clusters(ref, other, depth, camera, cfg)
    good = np.flatnonzero(n_cl >= cfg.min_cameras)
    if not len(good):
        return none, (pa, pb)
    remap = np.full(len(n_cl), -1)
    remap[good] = np.arange(len(good))
    keep = remap[cid] >= 0
    member_cluster = np.concatenate([remap[cid[keep]], np.arange(len(good))])
    member_blob = np.concatenate([other_k[keep], cluster_ref[good]])
    table = np.full((len(good), n_cams_rig), -1, dtype=np.int64)
    table[member_cluster, camera[member_blob]] = member_blob
    # each marker is found once from every camera that sees it: verify each set once
    table = np.unique(table, axis=0)
    table, tri = _prune(rig, arrays, table, camera, uv, cfg)
    n_seen = np.sum(table >= 0, axis=1)
    ok = (np.isfinite(tri.reproj_px) & (tri.reproj_px <= cfg.max_reproj_px)
          & (n_seen >= cfg.min_cameras))
    # rank: more cameras first, then the better reprojection
    order = np.lexsort((np.where(ok, tri.reproj_px, np.inf), -n_seen))
    rank = np.empty(len(table), dtype=np.int64)
    rank[order] = np.arange(len(table))
    point, cam = np.nonzero(table >= 0)
    sel = ok[point]
    accepted = _resolve(point[sel], table[point[sel], cam[sel]], rank, len(uv)) & ok
    return table[accepted], (pa, pb)


def match_frame(rig: Rig, camera: np.ndarray, uv: np.ndarray,
                config: CorrespondenceConfig | None = None) -> Matches:
    """Markers from the unlabelled blobs of one frame (camera index (M,), pixels (M, 2))."""
    cfg = config or CorrespondenceConfig()
    arrays = RigArrays.from_rig(rig)
    camera = np.asarray(camera, dtype=np.int64).reshape(-1)
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    n_cams_rig = len(rig)
    m = len(uv)
    empty = Matches(np.zeros((0, 3)), np.zeros(0), np.zeros(0), np.zeros(0, dtype=np.int64),
                    np.zeros((0, n_cams_rig), dtype=np.int64))
    if m < 2:
        return empty
    n = arrays.undistort(camera, uv)
    d_cam = np.concatenate([n, np.ones((m, 1))], axis=1)
    dirs = np.einsum("mji,mj->mi", arrays.R[camera], d_cam)
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    origins = arrays.centre[camera]
    used = np.zeros(m, dtype=bool)
    groups: list[np.ndarray] = []
    pairs = None
    # A second pass over the blobs left unused recovers markers whose clusters lost a
    # conflict with a neighbour's in the first.
    for _ in range(2):
        table, found_pairs = _cluster_pass(rig, arrays, camera, uv, n, origins, dirs, ~used, cfg)
        pairs = pairs or found_pairs
        if not len(table):
            break
        groups.append(table)
        used[table[table >= 0]] = True

    if cfg.two_camera and pairs is not None and len(pairs[0]):
        pa, pb = pairs
        # pairs unique both ways among all blobs, neither blob used by a 3+ camera marker
        partners = np.bincount(np.concatenate([pa, pb]), minlength=m)
        unique = (partners[pa] == 1) & (partners[pb] == 1) & ~used[pa] & ~used[pb]
        if np.any(unique):
            table = np.full((int(unique.sum()), n_cams_rig), -1, dtype=np.int64)
            rows = np.arange(len(table))
            table[rows, camera[pa[unique]]] = pa[unique]
            table[rows, camera[pb[unique]]] = pb[unique]
            groups.append(table)

    if not groups:
        return empty
    table = np.concatenate(groups)
    point, cam = np.nonzero(table >= 0)
    blob = table[point, cam]
    tri = triangulate(rig, point, cam, uv[blob], n_points=len(table))
    ok = np.isfinite(tri.reproj_px) & (tri.reproj_px <= cfg.max_reproj_px)
    two = np.sum(table >= 0, axis=1) == 2
    if np.any(two & ok):
        ok[two & ok] = ~_visible_elsewhere(rig, tri.xyz[two & ok], table[two & ok])
    return Matches(tri.xyz[ok], tri.reproj_px[ok], tri.ray_dist_m[ok], tri.n_cameras[ok],
                   table[ok])


def _visible_elsewhere(rig: Rig, xyz: np.ndarray, table: np.ndarray) -> np.ndarray:
    """True for points that some camera not in their match would have in its image: a real
    marker is then almost always seen by a third camera too, a chance pairing never."""
    seen = np.zeros(len(xyz), dtype=bool)
    for c, cam in enumerate(rig):
        uv, front = cam.project(xyz)
        seen |= front & cam.in_image(uv, margin_px=2.0) & (table[:, c] < 0)
    return seen


@dataclass(eq=False)
class FramePoints:
    """Markers of a whole recording, one row per point."""

    frame: np.ndarray  # (P,)
    xyz: np.ndarray
    reproj_px: np.ndarray
    ray_dist_m: np.ndarray
    n_cameras: np.ndarray
    rows: np.ndarray  # (P, C) row of the Observations table each point used, -1 if none


def match_frames(rig: Rig, obs: Observations, config: CorrespondenceConfig | None = None,
                 progress=None) -> FramePoints:
    """match_frame over every frame of a recording whose cameras are the rig's.

    `progress`, if given, is called with the number of frames done.
    """
    index = {name: i for i, name in enumerate(rig.names)}
    cam_map = np.array([index[name] for name in obs.camera_names], dtype=np.int64)
    order = np.argsort(obs.frame, kind="stable")
    frames = obs.frame[order]
    starts = np.flatnonzero(np.r_[True, frames[1:] != frames[:-1]])
    ends = np.r_[starts[1:], len(frames)]
    out_f, out_xyz, out_rep, out_ray, out_n, out_rows = [], [], [], [], [], []
    for k, (s, e) in enumerate(zip(starts, ends, strict=True)):
        rows = order[s:e]
        found = match_frame(rig, cam_map[obs.camera[rows]], obs.uv[rows], config)
        if len(found):
            out_f.append(np.full(len(found), frames[s]))
            out_xyz.append(found.xyz)
            out_rep.append(found.reproj_px)
            out_ray.append(found.ray_dist_m)
            out_n.append(found.n_cameras)
            out_rows.append(np.where(found.blobs >= 0, rows[np.maximum(found.blobs, 0)], -1))
        if progress is not None:
            progress(k + 1)
    if not out_f:
        return FramePoints(np.zeros(0, dtype=np.int64), np.zeros((0, 3)), np.zeros(0),
                           np.zeros(0), np.zeros(0, dtype=np.int64),
                           np.zeros((0, len(rig)), dtype=np.int64))
    return FramePoints(np.concatenate(out_f), np.concatenate(out_xyz), np.concatenate(out_rep),
                       np.concatenate(out_ray), np.concatenate(out_n),
                       np.concatenate(out_rows))
