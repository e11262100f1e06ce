"""Rigid bodies from files of 3D markers: the daemon's identification and pose, on a take.

Why: a file of 3D markers (our points CSV, a C3D, a Motive export) carries no
identities, and the rigid tracker keeps a body's tracks once it has found them; the
points get identities first (daemon.analysis.point_tracks), then every frame's tracks go through
the daemon's own `RigidTracker` with its definitions and settings, so the poses are the
ones the daemon would serve for those markers. A file has no 2D blobs, so the live
refinement on pixels does not run, and a hidden marker's track coasts on its own
prediction instead of being placed where its body puts it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from daemon.analysis.point_tracks import PointTrackConfig, PointTracker, TakeTracks
from daemon.formats.c3dio import Points
from daemon.tracking.rigid import BodyDef, RigidConfig, RigidTracker, quaternion_xyzw
from daemon.tracking.rigid_kernel import fit_bodies


@dataclass(eq=False)
class MarkerCloud:
    """Anonymous 3D markers per frame: xyz (F, P, 3) metres, NaN-padded to the busiest
    frame; frame numbers (F,) and times (F,) seconds."""

    frame: np.ndarray
    t_s: np.ndarray
    xyz: np.ndarray

    def __len__(self) -> int:
        return len(self.frame)

    def counts(self) -> np.ndarray:
        return np.isfinite(self.xyz).all(axis=2).sum(axis=1)


def cloud_from_points(points: Points, rate_hz: float) -> MarkerCloud:
    """Points (one row each, with its frame) packed frame by frame; t_s = frame / rate_hz.
    Frames with no point in the file do not appear (there is nothing to pose there)."""
    order = np.argsort(points.frame, kind="stable")
    frame = np.asarray(points.frame)[order]
    xyz = np.asarray(points.xyz_m, dtype=np.float64)[order]
    frames, start, count = np.unique(frame, return_index=True, return_counts=True)
    row = np.repeat(np.arange(len(frames)), count)
    slot = np.arange(len(frame)) - start[row]
    out = np.full((len(frames), max(int(count.max(initial=0)), 1), 3), np.nan)
    out[row, slot] = xyz
    return MarkerCloud(frames.astype(np.int64), frames / float(rate_hz), out)


def cloud_from_arrays(xyz: np.ndarray, t_s: np.ndarray, frame: np.ndarray) -> MarkerCloud:
    """Markers (F, P, 3) with NaN where not seen, compacted so each frame's points come
    first (the order within a frame carries no identity)."""
    xyz = np.asarray(xyz, dtype=np.float64)
    seen = np.isfinite(xyz).all(axis=2)
    order = np.argsort(~seen, axis=1, kind="stable")
    xyz = np.take_along_axis(xyz, order[:, :, None], axis=1)
    width = max(int(seen.sum(axis=1).max(initial=0)), 1)
    out = xyz[:, :width].copy()
    out[~np.isfinite(out).all(axis=2)] = np.nan
    return MarkerCloud(np.asarray(frame, dtype=np.int64), np.asarray(t_s, dtype=np.float64),
                       out)


@dataclass(eq=False)
class TrackResult:
    """Poses of every body in every frame of a take (bodies in definition order)."""

    frame: np.ndarray  # (F,)
    t_s: np.ndarray  # (F,)
    names: list[str]
    ids: np.ndarray  # (B,)
    valid: np.ndarray  # (F, B) bool
    position: np.ndarray  # (F, B, 3) metres, NaN when invalid
    quaternion: np.ndarray  # (F, B, 4) x y z w, NaN when invalid
    error_m: np.ndarray  # (F, B) mean marker distance from its fitted place, NaN invalid
    n_markers: np.ndarray  # (F, B)
    markers_seen: np.ndarray  # (F,) points in the frame


def track_cloud(cloud: MarkerCloud, bodies: list[BodyDef],
                rigid_config: RigidConfig | None = None,
                point_config: PointTrackConfig | None = None,
                progress=None, batched: bool = True) -> TrackResult:
    """Run the daemon's rigid tracker over every frame of `cloud` (a whole take at once);
    progress(frames done) is called as it goes. See CloudTracker."""
    return CloudTracker(bodies, rigid_config, point_config, batched).window(cloud, progress)


class CloudTracker:
    """The daemon's rigid tracker over a take, fed whole or a window of frames at a time.

    Frame by frame this is `RigidTracker.update(tracks)` as live. Most frames change
    nothing in the tracker's state (every body keeps its tracks, none is released, no free
    track sits where a body misses a marker, no lost body has enough free points to be
    searched for): such runs of frames are fitted at once with the tracker's own compiled
    kernel, and only the frames where something may change go through update() itself.
    `batched=False` sends every frame through update().

    Why windows need no overlap: everything a frame's result depends on from the frames
    before it is state carried here (the point tracks' positions, velocities and ids in
    PointTracker; the bodies' assigned tracks, poses and frame count in RigidTracker), and
    a steady run cut at a window's edge gives the poses update() would, frame by frame. So
    a take tracked in windows gets the poses of the whole take tracked at once.
    """

    def __init__(self, bodies: list[BodyDef], rigid_config: RigidConfig | None = None,
                 point_config: PointTrackConfig | None = None, batched: bool = True) -> None:
        cfg = rigid_config or RigidConfig(refine=False)
        self.bodies = list(bodies)
        self.points = PointTracker(point_config)
        self.rigid = RigidTracker(self.bodies, cfg)
        self.fast = (batched and cfg.compiled and bool(self.bodies)
                     and all(b.smoothing == 0 for b in self.bodies))
        self.length = 64  # frames tried at once: doubled after a steady run, halved after
        self.frames_done = 0  # frames of the take tracked so far (windows before this)

    def window(self, cloud: MarkerCloud, progress=None) -> TrackResult:
        """The poses of the next frames of the take (after those of the last window);
        progress(frames of the take done) is called as it goes."""
        tracks = self.points.window(cloud.xyz, cloud.counts(), cloud.frame)
        rigid, fast = self.rigid, self.fast
        out = _Poses(len(cloud), len(self.bodies))
        n_frames = len(cloud)
        f = reported = 0
        while f < n_frames:
            if fast:
                end = min(f + self.length, n_frames)
                done = _steady_run(rigid, tracks, f, end, out)
                rigid.frame += done
                f += done
                self.length = (min(2 * self.length, MAX_RUN) if f == end
                               else max(self.length // 2, MIN_RUN))
            if f < n_frames and not (fast and f == end):
                out.put(f, rigid.update(tracks.tracks_at(f)))
                f += 1
            if progress is not None and (f - reported >= 1024 or f == n_frames):
                progress(self.frames_done + f)
                reported = f
        self.frames_done += n_frames
        return TrackResult(cloud.frame, cloud.t_s, [b.name for b in self.bodies],
                           np.array([b.id for b in self.bodies], dtype=np.int64), out.valid,
                           out.position, out.quaternion, out.error_m, out.n_markers,
                           cloud.counts())


class _Poses:
    """The output arrays, filled frame by frame or a run at a time."""

    def __init__(self, n_frames: int, n_bodies: int) -> None:
        self.valid = np.zeros((n_frames, n_bodies), dtype=bool)
        self.position = np.full((n_frames, n_bodies, 3), np.nan)
        self.quaternion = np.full((n_frames, n_bodies, 4), np.nan)
        self.error_m = np.full((n_frames, n_bodies), np.nan)
        self.n_markers = np.zeros((n_frames, n_bodies), dtype=np.int64)

    def put(self, f, poses) -> None:
        self.valid[f] = poses.valid
        self.position[f] = poses.position
        self.quaternion[f] = poses.quaternion
        self.error_m[f] = poses.error_m
        self.n_markers[f] = poses.n_markers


MIN_RUN, MAX_RUN = 8, 4096  # frames fitted at once: the least worth the overhead, the most
_ID_SPAN = np.int64(1) << 40  # frame * _ID_SPAN + track id orders a run's rows


def _search_may_succeed(rigid, tracks, s0, local, free, row, seen, fi, bi) -> np.ndarray:
    """For lost body bi[j] in run frame fi[j]: False where RigidTracker._identify's search
    (find_body) must fail, so skipping it changes nothing. find_body needs `need` points
    each at a distance of one of the body's own (within distance_tol_m) from at least
    need - 1 others of its pool (the free seen tracks and the body's own seen ones); with
    fewer such points no assignment exists. Batched over the (frame, body) pairs."""
    tol = rigid.config.distance_tol_m
    free_rows = np.flatnonzero(free)
    n_free = np.bincount(local[free_rows], minlength=int(fi.max()) + 1)
    first = np.concatenate([[0], np.cumsum(n_free)[:-1]])
    wf = max(int(n_free[fi].max()), 1)
    slot = np.arange(wf)
    idx_free = free_rows[np.minimum(first[fi, None] + slot, len(free_rows) - 1)] \
        if len(free_rows) else np.zeros((len(fi), wf), np.int64)
    ok_free = slot < n_free[fi, None]
    idx = np.concatenate([s0 + idx_free, row[fi, bi]], axis=1)  # (M, W)
    mask = np.concatenate([ok_free, seen[fi, bi]], axis=1)
    pts = tracks.xyz[idx]
    d = np.linalg.norm(pts[:, :, None] - pts[:, None], axis=3)  # (M, W, W)
    k = max(len(b.markers) for b in rigid.bodies)
    bd = np.full((len(rigid.bodies), k * (k - 1) // 2), np.nan)
    need = np.zeros(len(rigid.bodies), dtype=np.int64)
    for i, body in enumerate(rigid.bodies):  # per body definition, not per frame
        kb = len(body.markers)
        bd[i, :kb * (kb - 1) // 2] = body.distances[np.triu_indices(kb, 1)]
        need[i] = max(3, min(body.min_markers_start, kb))
    fits = (np.abs(d[..., None] - bd[bi][:, None, None, :]) < tol).any(axis=3)
    fits &= mask[:, :, None] & mask[:, None, :]
    fits &= ~np.eye(idx.shape[1], dtype=bool)[None]
    partners = fits.sum(axis=2)
    return np.sum(partners >= (need[bi] - 1)[:, None], axis=1) >= need[bi]


def _steady_run(rigid: RigidTracker, tracks: TakeTracks, a: int, b: int, out: _Poses) -> int:
    """Fit frames a..b-1 at once with the tracker's state as it is, up to the first frame
    where update() might change that state; their poses go to `out`. Returns how many
    frames were done (0 when frame a itself needs update())."""
    n = b - a
    B = len(rigid.bodies)
    cfg = rigid.config
    assigned = rigid.assigned  # (B, K)
    s0, s1 = int(tracks.start[a]), int(tracks.start[b])
    per = np.diff(tracks.start[a:b + 1])
    local = np.repeat(np.arange(n, dtype=np.int64), per)
    key = local * _ID_SPAN + tracks.ids[s0:s1]
    has = assigned >= 0
    if len(key):
        want = np.arange(n, dtype=np.int64)[:, None, None] * _ID_SPAN + assigned[None]
        pos = np.minimum(np.searchsorted(key, want), len(key) - 1)
        exists = has[None] & (key[pos] == want)
    else:
        pos = np.zeros((n,) + assigned.shape, dtype=np.int64)
        exists = np.zeros((n,) + assigned.shape, dtype=bool)
    row = s0 + pos
    gone = (has[None] & ~exists).any(axis=(1, 2))  # update() would release these slots
    seen = exists & tracks.seen[row]
    dst = tracks.xyz[row]
    K = assigned.shape[1]
    markers = np.broadcast_to(rigid.markers, (n, B, K, 3)).reshape(n * B, K, 3)
    R, t, err, used, released = fit_bodies(
        np.ascontiguousarray(markers), dst.reshape(n * B, K, 3), seen.reshape(n * B, K),
        np.zeros((n * B, K)), False, cfg.max_error_m, 3)
    R, t = R.reshape(n, B, 3, 3), t.reshape(n, B, 3)
    count = used.reshape(n, B, K).sum(axis=2)
    valid = count >= np.maximum(rigid.keep_min, 3)[None]
    bad = gone | released.reshape(n, B, K).any(axis=(1, 2))
    # free tracks: seen and no body's; what _extend and _identify would look at
    taken = np.isin(tracks.ids[s0:s1], assigned[has])
    free = tracks.seen[s0:s1] & ~taken
    n_free = np.bincount(local[free], minlength=n)
    # a free track near a missing marker of a valid body
    slot_free = valid[:, :, None] & rigid.slot[None] & ~has[None]  # (n, B, K)
    if slot_free.any() and free.any():
        width = int(n_free.max())
        fl = local[free]
        rank = np.arange(len(fl)) - np.searchsorted(fl, fl)
        cand = np.full((n, width, 3), np.inf)
        cand[fl, rank] = tracks.xyz[s0:s1][free]
        fi, bi, ki = np.nonzero(slot_free)
        where = np.einsum("nij,nj->ni", R[fi, bi], rigid.markers[bi, ki]) + t[fi, bi]
        d = np.linalg.norm(where[:, None, :] - cand[fi], axis=2)
        near = (d < cfg.max_error_m).any(axis=1)
        bad[fi[near]] = True
    # a lost body with enough points to search among, unless its search must fail
    pool = n_free[:, None] + seen.sum(axis=2)
    need = np.array([min(bd.min_markers_start, len(bd.markers)) for bd in rigid.bodies])
    first = int(np.argmax(bad)) if bad.any() else n  # only frames before it matter
    fi, bi = np.nonzero(~valid[:first] & (pool[:first] >= need[None]))
    lo, step = 0, 8
    while lo < len(fi):  # in growing blocks of frames: the first possible search ends the run
        hi = int(np.searchsorted(fi, fi[lo] + step))
        may = _search_may_succeed(rigid, tracks, s0, local, free, row, seen, fi[lo:hi],
                                  bi[lo:hi])
        if may.any():
            bad[fi[lo:hi][may]] = True
            break
        lo, step = hi, 2 * step
    done = int(np.argmax(bad)) if bad.any() else n
    if done:
        sl = slice(a, a + done)
        Rd, td, vd = R[:done].reshape(-1, 3, 3), t[:done].reshape(-1, 3), valid[:done]
        position = (np.einsum("bij,bj->bi", Rd, np.tile(rigid.pivot, (done, 1)))
                    + td).reshape(done, B, 3)
        q = quaternion_xyzw(Rd).reshape(done, B, 4)
        position[~vd] = np.nan
        q[~vd] = np.nan
        out.valid[sl] = vd
        out.position[sl] = position
        out.quaternion[sl] = q
        out.error_m[sl] = np.where(vd, err.reshape(n, B)[:done], np.nan)
        out.n_markers[sl] = count[:done]
    return done


def _stats_mm(v: np.ndarray) -> dict:
    v = v[np.isfinite(v)]
    if not len(v):
        return {"rms": None, "median": None, "p95": None, "max": None, "count": 0}
    return {"rms": float(np.sqrt(np.mean(v * v))), "median": float(np.median(v)),
            "p95": float(np.percentile(v, 95)), "max": float(v.max()), "count": int(len(v))}


def figures(result: TrackResult, gross_error_mm: float = 20.0) -> dict:
    """The figures live tracking reports, per body and over all: frames, poses found, the
    valid fraction, the fit error of the markers, and fits worse than gross_error_mm (a
    body posed on a wrong marker) counted apart."""
    return figures_of(PoseFigures(result.names, result.ids, result.valid, result.error_m,
                                  result.n_markers, result.markers_seen), gross_error_mm)


@dataclass(eq=False)
class PoseFigures:
    """What the figures are made of, per frame (F,) and body (F, B): all a take tracked in
    windows keeps of its poses once they are written (13 bytes a frame and body, with
    n_markers as int32)."""

    names: list[str]
    ids: np.ndarray
    valid: np.ndarray
    error_m: np.ndarray
    n_markers: np.ndarray
    markers_seen: np.ndarray


def figures_of(result: PoseFigures, gross_error_mm: float = 20.0) -> dict:
    """figures() from the figures' arrays alone."""
    n = len(result.markers_seen)
    err_mm = result.error_m * 1000.0
    bodies = {}
    for b, name in enumerate(result.names):
        valid = result.valid[:, b]
        e = err_mm[valid, b]
        bodies[name] = {
            "id": int(result.ids[b]), "frames": n, "poses": int(valid.sum()),
            "valid_fraction": float(valid.mean()) if n else 0.0,
            "gross_fit_errors": int(np.sum(e > gross_error_mm)),
            "fit_error_mm": _stats_mm(e),
            "markers_median": float(np.median(result.n_markers[valid, b])) if valid.any()
            else 0.0,
        }
    valid = result.valid
    return {
        "frames": n,
        "bodies_defined": len(result.names),
        "poses": int(valid.sum()),
        "valid_fraction": float(valid.mean()) if valid.size else 0.0,
        "gross_fit_errors": int(np.sum(err_mm[valid] > gross_error_mm)),
        "gross_limit_mm": gross_error_mm,
        "fit_error_mm": _stats_mm(err_mm[valid]),
        "markers_median": float(np.median(result.markers_seen)) if n else 0.0,
        "bodies_valid_fraction": {str(int(i)): bodies[nm]["valid_fraction"]
                                  for i, nm in zip(result.ids, result.names, strict=True)},
        "bodies": bodies,
    }


def rotation_difference_deg(qa: np.ndarray, qb: np.ndarray) -> np.ndarray:
    """Angles (deg) between unit quaternions (..., 4) x y z w (either sign)."""
    dot = np.abs(np.sum(qa * qb, axis=-1))
    return np.degrees(2 * np.arccos(np.clip(dot, 0.0, 1.0)))


def compare_poses(result: TrackResult, name: str, frame: np.ndarray, valid: np.ndarray,
                  xyz: np.ndarray, quat: np.ndarray, gross_mm: float = 20.0,
                  gross_deg: float = 5.0) -> dict:
    """Our poses of body `name` against another system's (frame numbers, valid, xyz, quat):
    differences where both have a pose, and the frames only one of them has. The limits
    are the live evaluator's (2 cm, 5 degrees)."""
    b = result.names.index(name)
    ours = {int(f): i for i, f in enumerate(result.frame.tolist())}
    rows = np.array([ours.get(int(f), -1) for f in frame], dtype=np.int64)
    have = rows >= 0
    mine = np.zeros(len(frame), dtype=bool)
    mine[have] = result.valid[rows[have], b]
    both = mine & valid
    r = rows[both]
    dp = np.linalg.norm(result.position[r, b] - xyz[both], axis=1) * 1000.0
    da = rotation_difference_deg(result.quaternion[r, b], quat[both])
    return {
        "frames_both": int(both.sum()), "frames_only_theirs": int(np.sum(valid & ~mine)),
        "frames_only_ours": int(np.sum(mine & ~valid)),
        "position_mm": _stats_mm(dp), "orientation_deg": _stats_mm(da),
        "gross": int(np.sum((dp > gross_mm) | (da > gross_deg))),
        "gross_limits": [gross_mm, gross_deg],
    }
