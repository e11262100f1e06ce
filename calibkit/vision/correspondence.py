"""Which blobs in different cameras are the same marker: epipolar matching of unlabelled blobs.

The seed thesis's method, over many frames at once: every blob's candidates are the blobs
near its epipolar line in the other cameras of its frame (a compiled kernel; the numpy
reference finds the same pairs by sorting epipolar-plane angles); each candidate's ray meets
the blob's ray at a point along it; those points are clustered by depth, and a cluster seen
by >= 3 cameras is a marker. Clusters are verified by triangulation (their rays must really
meet), then accepted best first with each blob used at most once. Two-camera matches are
added only where the pairing is unique both ways, because two rays always "meet" somewhere
on the epipolar line and a ghost is otherwise indistinguishable from a marker.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calibkit.core.camera import Rig
from calibkit.core.geometry import RigArrays, Triangulation, triangulate
from calibkit.core.observations import Observations


@dataclass(frozen=True)
class CorrespondenceConfig:
    epipolar_px: float = 2.0  # how far a candidate may lie from the epipolar line
    cluster_m: float = 0.01  # gap along the ray that separates two clusters (+1 % of depth)
    max_reproj_px: float = 1.5  # a cluster whose rays do not meet this well is a ghost
    min_cameras: int = 3
    two_camera: bool = True  # also accept unambiguous pairs
    compiled: bool = True  # numba kernels; False runs the numpy reference implementation


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


_CACHE: dict[tuple[int, str], tuple[RigArrays, np.ndarray]] = {}


def _cached(arrays: RigArrays, make) -> np.ndarray:
    """make(arrays), computed once per rig's arrays (they are immutable)."""
    key = (id(arrays), make.__name__)
    hit = _CACHE.get(key)
    if hit is None or hit[0] is not arrays:
        hit = (arrays, make(arrays))
        _CACHE[key] = hit
    return hit[1]


def _baseline_bases(arrays: RigArrays) -> np.ndarray:
    """(C, C, 2, 3): for each camera pair, two unit vectors perpendicular to the baseline
    (the same for (i, j) and (j, i)), in which a ray's epipolar plane is an angle."""
    c = len(arrays.centre)
    bases = np.zeros((c, c, 2, 3))
    for i in range(c):
        for j in range(i + 1, c):
            base = arrays.centre[j] - arrays.centre[i]
            base /= np.linalg.norm(base)
            e1 = np.cross(base, [1.0, 0.0, 0.0] if abs(base[0]) < 0.9 else [0.0, 1.0, 0.0])
            e1 /= np.linalg.norm(e1)
            bases[i, j] = bases[j, i] = (e1, np.cross(base, e1))
    return bases


def _pairs(arrays: RigArrays, group: np.ndarray, camera: np.ndarray, n: np.ndarray,
           origins: np.ndarray, dirs: np.ndarray, tol_px: float, compiled: bool = True):
    """Candidate blob pairs (a, b) in different cameras of the same group (frame) whose
    epipolar distance is below tol_px both ways, and the depths along each ray where the
    two rays pass closest. The compiled kernel tests every pair of a frame's blobs (a few
    flops each); the numpy path narrows them down by sorting first (see _pairs_numpy)."""
    if not compiled:
        return _pairs_numpy(arrays, group, camera, n, origins, dirs, tol_px)
    # deferred on purpose: loads numba (compiled kernels) only where used
    from calibkit.core.geometry_kernels import epipolar_pairs

    if len(camera) < 2:
        empty = np.zeros(0, dtype=np.int64)
        return empty, empty, np.zeros(0), np.zeros(0)
    E = _cached(arrays, _essentials)
    order = np.argsort(group * 1024 + camera, kind="stable")
    g, c = group[order], camera[order]
    homog = np.concatenate([n[order], np.ones((len(n), 1))], axis=1)
    lines = np.einsum("mcab,mb->mca", E[c], homog)  # (M, C, 3): line in each camera
    lines *= (arrays.fx[None, :] / np.maximum(np.hypot(lines[..., 0], lines[..., 1]),
                                               1e-15))[..., None]
    new = np.r_[True, (g[1:] != g[:-1]) | (c[1:] != c[:-1])]
    block_start = np.r_[np.flatnonzero(new), len(g)].astype(np.int64)
    args = (block_start, c[new], g[new], lines, homog, np.ascontiguousarray(origins[order]),
            np.ascontiguousarray(dirs[order]), float(tol_px))
    count, pa, pb, s, u = epipolar_pairs(*args, 16 * len(g) + 64)
    if count > len(pa):
        count, pa, pb, s, u = epipolar_pairs(*args, count)
    return order[pa[:count]], order[pb[:count]], s[:count], u[:count]


def _pairs_numpy(arrays: RigArrays, group: np.ndarray, camera: np.ndarray, n: np.ndarray,
                 origins: np.ndarray, dirs: np.ndarray, tol_px: float):
    """Candidate blob pairs (a, b) in different cameras of the same group (frame) whose
    epipolar distance is below tol_px both ways, and the depths along each ray where the
    two rays pass closest.

    Two rays can only meet if they lie in the same plane through both camera centres, so
    matching blobs share that plane's angle about the baseline; a pixel of epipolar
    distance turns the plane by about 1 / (f sin(ray-to-baseline angle)). Per camera pair,
    one camera's blobs are sorted by (group, angle) and each blob of the other camera
    searches its window (twice as wide as the tolerance asks, for lens distortion): a
    sort instead of testing every pair. The exact epipolar test then runs on those only.
    """
    E = _cached(arrays, _essentials)
    bases = _cached(arrays, _baseline_bases)
    n_cams = len(arrays.centre)
    homog = np.concatenate([n, np.ones((len(n), 1))], axis=1)
    cams = np.unique(camera)
    idx = {int(c): np.flatnonzero(camera == c) for c in cams}
    theta, sin_base = {}, {}
    for c in cams:
        xy = (dirs[idx[int(c)]] @ bases[c].reshape(-1, 3).T).reshape(-1, n_cams, 2)
        theta[int(c)] = np.arctan2(xy[..., 1], xy[..., 0])
        sin_base[int(c)] = np.hypot(xy[..., 0], xy[..., 1])
    band = 20.0  # group g's keys lie in [20 g - 2 pi, 20 g + 4 pi]: bands never overlap
    out_a, out_b = [], []
    for ii, ci in enumerate(cams):
        a = idx[int(ci)]
        for cj in cams[ii + 1:]:
            b = idx[int(cj)]
            key_b = band * group[b] + theta[int(cj)][:, ci]
            # copies shifted by a full turn catch windows that cross +-pi
            keys = np.concatenate([key_b - 2 * np.pi, key_b, key_b + 2 * np.pi])
            order = np.argsort(keys)
            keys = keys[order]
            window = np.minimum(
                2.0 * tol_px / (arrays.fx[ci] * np.maximum(sin_base[int(ci)][:, cj], 1e-9)),
                np.pi)
            key_a = band * group[a] + theta[int(ci)][:, cj]
            lo = np.searchsorted(keys, key_a - window)
            counts = np.searchsorted(keys, key_a + window, side="right") - lo
            total = int(counts.sum())
            if not total:
                continue
            ia = np.repeat(np.arange(len(a)), counts)
            ib = order[np.repeat(lo - np.cumsum(counts) + counts, counts)
                       + np.arange(total)] % len(b)
            # exact epipolar distances, in pixels of the camera each line is drawn in
            ha, hb = homog[a], homog[b]
            lines_b = ha @ E[ci, cj].T  # in camera cj
            lines_b *= (arrays.fx[cj] / np.maximum(np.hypot(lines_b[:, 0], lines_b[:, 1]),
                                                    1e-15))[:, None]
            lines_a = hb @ E[ci, cj]  # in camera ci
            lines_a *= (arrays.fx[ci] / np.maximum(np.hypot(lines_a[:, 0], lines_a[:, 1]),
                                                    1e-15))[:, None]
            dj = np.abs(np.einsum("pk,pk->p", lines_b[ia], hb[ib]))
            di = np.abs(np.einsum("pk,pk->p", lines_a[ib], ha[ia]))
            keep = np.maximum(di, dj) < tol_px
            out_a.append(a[ia[keep]])
            out_b.append(b[ib[keep]])
    if not out_a:
        empty = np.zeros(0, dtype=np.int64)
        return empty, empty, np.zeros(0), np.zeros(0)
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
    front = (s > 0) & (u > 0)
    return pa[front], pb[front], s[front], u[front]


def _clusters(ref: np.ndarray, other: np.ndarray, depth: np.ndarray, camera: np.ndarray,
              cfg: CorrespondenceConfig):
    """Cluster each reference blob's candidates by depth along its ray.

    Returns (cluster id per kept candidate, reference blob per cluster, kept candidates,
    cameras per cluster) with at most one candidate per camera in a cluster (the one
    nearest the cluster's mean depth).
    """
    # sort by reference blob, then depth (metres, far below 1e4): one float key sorts
    # several times faster than np.lexsort
    order = np.argsort(ref * 1e4 + depth, kind="stable")
    ref, other, depth = ref[order], other[order], depth[order]
    gap = np.diff(depth) > cfg.cluster_m + 0.01 * depth[1:]
    new = np.r_[True, (ref[1:] != ref[:-1]) | gap]
    cid = np.cumsum(new) - 1
    n_clusters = int(cid[-1]) + 1 if len(cid) else 0
    mean = np.bincount(cid, weights=depth, minlength=n_clusters) / np.maximum(
        np.bincount(cid, minlength=n_clusters), 1)
    dev = np.abs(depth - mean[cid])
    cam = camera[other]
    keep_order = np.argsort((cid * 64.0 + cam) * 1e4 + np.minimum(dev, 1e3), kind="stable")
    first = np.r_[True, (cid[keep_order][1:] != cid[keep_order][:-1])
                  | (cam[keep_order][1:] != cam[keep_order][:-1])]
    kept = keep_order[first]
    cid_k, other_k = cid[kept], other[kept]
    cluster_ref = ref[new]
    n_cams = np.bincount(cid_k, minlength=n_clusters) + 1
    return cid_k, cluster_ref, other_k, n_cams


def _unique_rows(table: np.ndarray) -> np.ndarray:
    """Distinct rows of an integer table, by a random 64-bit hash of each row: far faster
    than np.unique(axis=0); a collision (about 1e-19 per pair) would only merge two
    candidate sets."""
    if len(table) < 2:
        return table
    weights = np.random.default_rng(12345).integers(1, 2**62, table.shape[1], dtype=np.int64)
    with np.errstate(over="ignore"):
        key = (table + 1) @ weights
    _, first = np.unique(key, return_index=True)
    return table[np.sort(first)]


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
           origins: np.ndarray, dirs: np.ndarray, cfg: CorrespondenceConfig,
           rounds: int = 2) -> tuple[np.ndarray, Triangulation]:
    """Triangulate candidate markers (rows of `table`) and drop, per round, each one's worst
    observation if it misses by more than max_reproj_px: one wrong blob among eight cameras
    hides in a point's RMS but not in its own residual. Only rows that lost a blob are
    triangulated again."""
    table = table.copy()
    rows = np.arange(len(table))
    tri = None
    for _ in range(rounds + 1):
        sub = table[rows]
        point, cam = np.nonzero(sub >= 0)
        blob = sub[point, cam]
        part = triangulate(rig, point, cam, uv[blob], iterations=1, n_points=len(sub),
                           ray_distance=False, rays=(origins[blob], dirs[blob]),
                           compiled=cfg.compiled)
        if tri is None:
            tri = part
        else:
            for name in ("xyz", "reproj_px", "ray_dist_m", "n_cameras"):
                getattr(tri, name)[rows] = getattr(part, name)
        proj, _ = arrays.project(cam, np.nan_to_num(part.xyz[point]))
        resid = np.linalg.norm(proj - uv[blob], axis=1)
        worst = np.full(len(sub), -1.0)
        np.maximum.at(worst, point, resid)
        drop = (resid == worst[point]) & (resid > cfg.max_reproj_px)
        if not np.any(drop):
            break
        table[rows[point[drop]], cam[drop]] = -1
        rows = np.unique(rows[point[drop]])
    return table, tri


def _cluster_pass(rig: Rig, arrays: RigArrays, group: np.ndarray, camera: np.ndarray,
                  uv: np.ndarray, n: np.ndarray, origins: np.ndarray, dirs: np.ndarray,
                  available: np.ndarray, cfg: CorrespondenceConfig
                  ) -> tuple[np.ndarray, np.ndarray, tuple]:
    """Markers seen by >= min_cameras among the `available` blobs: (P, C) blob table, their
    first positions, and the candidate pairs found (for the two-camera step)."""
    n_cams_rig = len(rig)
    sub = np.flatnonzero(available)
    pa, pb, s, u = _pairs(arrays, group[sub], camera[sub], n[sub], origins[sub],
                          dirs[sub], cfg.epipolar_px, cfg.compiled)
    pa, pb = sub[pa], sub[pb]
    none = np.zeros((0, n_cams_rig), dtype=np.int64)
    if not len(pa) or cfg.min_cameras > n_cams_rig:
        return none, np.zeros((0, 3)), (pa, pb)
    ref = np.concatenate([pa, pb])
    other = np.concatenate([pb, pa])
    depth = np.concatenate([s, u])
    cid, cluster_ref, other_k, n_cl = _clusters(ref, other, depth, camera, cfg)
    good = np.flatnonzero(n_cl >= cfg.min_cameras)
    if not len(good):
        return none, np.zeros((0, 3)), (pa, pb)
    remap = np.full(len(n_cl), -1)
    remap[good] = np.arange(len(good))
    keep = remap[cid] >= 0
    member_cluster = np.concatenate([remap[cid[keep]], np.arange(len(good))])
    member_blob = np.concatenate([other_k[keep], cluster_ref[good]])
    table = np.full((len(good), n_cams_rig), -1, dtype=np.int64)
    table[member_cluster, camera[member_blob]] = member_blob
    # each marker is found once from every camera that sees it: verify each set once
    table = _unique_rows(table)
    table, tri = _prune(rig, arrays, table, camera, uv, origins, dirs, cfg)
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
    return table[accepted], tri.xyz[accepted], (pa, pb)


def match_frame(rig: Rig, camera: np.ndarray, uv: np.ndarray,
                config: CorrespondenceConfig | None = None) -> Matches:
    """Markers from the unlabelled blobs of one frame (camera index (M,), pixels (M, 2))."""
    camera = np.asarray(camera, dtype=np.int64).reshape(-1)
    found, _ = match_groups(rig, np.zeros(len(camera), dtype=np.int64), camera, uv, config)
    return found


def match_groups(rig: Rig, group: np.ndarray, camera: np.ndarray, uv: np.ndarray,
                 config: CorrespondenceConfig | None = None) -> tuple[Matches, np.ndarray]:
    """match_frame for many frames at once: blobs only pair with blobs of the same `group`
    (frame number). Returns the markers and the group of each; doing a batch of frames in
    one pass removes the per-frame Python overhead that otherwise dominates."""
    cfg = config or CorrespondenceConfig()
    group = np.asarray(group, dtype=np.int64).reshape(-1)
    arrays = RigArrays.from_rig(rig)
    camera = np.asarray(camera, dtype=np.int64).reshape(-1)
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    n_cams_rig = len(rig)
    m = len(uv)
    empty = Matches(np.zeros((0, 3)), np.zeros(0), np.zeros(0), np.zeros(0, dtype=np.int64),
                    np.zeros((0, n_cams_rig), dtype=np.int64))
    if m < 2:
        return empty, np.zeros(0, dtype=np.int64)
    n = arrays.undistort(camera, uv)
    d_cam = np.concatenate([n, np.ones((m, 1))], axis=1)
    dirs = np.einsum("mji,mj->mi", arrays.R[camera], d_cam)
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    origins = arrays.centre[camera]
    used = np.zeros(m, dtype=bool)
    tables: list[np.ndarray] = []
    starts: list[np.ndarray] = []
    pairs = None
    # A second pass over the blobs left unused recovers markers whose clusters lost a
    # conflict with a neighbour's in the first.
    for _ in range(2):
        table, xyz, found_pairs = _cluster_pass(rig, arrays, group, camera, uv, n, origins,
                                                 dirs, ~used, cfg)
        pairs = pairs or found_pairs
        if not len(table):
            break
        tables.append(table)
        starts.append(xyz)
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
            tables.append(table)
            starts.append(np.full((len(table), 3), np.nan))

    if not tables:
        return empty, np.zeros(0, dtype=np.int64)
    table = np.concatenate(tables)
    point, cam = np.nonzero(table >= 0)
    blob = table[point, cam]
    tri = triangulate(rig, point, cam, uv[blob], iterations=1, n_points=len(table),
                      rays=(origins[blob], dirs[blob]), start=np.concatenate(starts),
                      compiled=cfg.compiled)
    ok = np.isfinite(tri.reproj_px) & (tri.reproj_px <= cfg.max_reproj_px)
    two = np.sum(table >= 0, axis=1) == 2
    if np.any(two & ok):
        ok[two & ok] = ~_visible_elsewhere(rig, tri.xyz[two & ok], table[two & ok])
    table = table[ok]
    return (Matches(tri.xyz[ok], tri.reproj_px[ok], tri.ray_dist_m[ok], tri.n_cameras[ok], table),
            group[table.max(axis=1)])


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
                 progress=None, chunk_frames: int = 32) -> FramePoints:
    """Markers of every frame of a recording whose cameras are the rig's, matched
    `chunk_frames` frames at a time (see match_groups).

    `progress`, if given, is called with the number of frames done.
    """
    index = {name: i for i, name in enumerate(rig.names)}
    cam_map = np.array([index[name] for name in obs.camera_names], dtype=np.int64)
    order = np.argsort(obs.frame, kind="stable")
    frames = obs.frame[order]
    starts = np.flatnonzero(np.r_[True, frames[1:] != frames[:-1]])
    bounds = np.r_[starts[::chunk_frames], len(frames)]
    parts: list[tuple] = []
    for k in range(len(bounds) - 1):
        rows = order[bounds[k]:bounds[k + 1]]
        found, group = match_groups(rig, obs.frame[rows], cam_map[obs.camera[rows]],
                                    obs.uv[rows], config)
        if len(found):
            parts.append((group, found.xyz, found.reproj_px, found.ray_dist_m,
                          found.n_cameras,
                          np.where(found.blobs >= 0, rows[np.maximum(found.blobs, 0)], -1)))
        if progress is not None:
            progress(min((k + 1) * chunk_frames, len(starts)))
    if not parts:
        return FramePoints(np.zeros(0, dtype=np.int64), np.zeros((0, 3)), np.zeros(0),
                           np.zeros(0), np.zeros(0, dtype=np.int64),
                           np.zeros((0, len(rig)), dtype=np.int64))
    cat = [np.concatenate(column) for column in zip(*parts, strict=True)]
    points = FramePoints(*cat)
    by_frame = np.argsort(points.frame, kind="stable")
    return FramePoints(*(getattr(points, f)[by_frame] for f in
                         ("frame", "xyz", "reproj_px", "ray_dist_m", "n_cameras", "rows")))
