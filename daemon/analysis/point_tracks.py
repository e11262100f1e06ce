"""Identities for anonymous 3D markers of a whole take: the tracks the rigid tracker needs.

Why: the live tracker keeps identities from 2D blobs; a file of 3D markers (our points
CSV, a C3D, a Motive export) has none, and the rigid tracker keeps a body's tracks once it
has found them. Here each track is predicted at constant velocity, a point and a track are
paired when each is the other's nearest within the gate, unpaired points start new tracks
(ids only grow, so each frame's tracks stay sorted by id) and a track unseen for more than
max_missing frames is dropped, as live. A take runs in one compiled loop, whole or a
window at a time (PointTracker carries the live tracks from one window to the next); the
result is every frame's tracks in one flat table (CSR: frame f's rows are
start[f]:start[f + 1]), from which `tracks_at` makes the live TrackFrame of any frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calibkit.core.jit import jit
from daemon.tracking.tracker import TrackFrame


@dataclass(frozen=True)
class PointTrackConfig:
    gate_m: float = 0.03  # a point this far from a track's prediction is not its own
    max_missing: int = 24  # frames a track coasts before it is dropped (the live default)
    velocity_alpha: float = 0.7  # weight of the newest velocity estimate (as live)


@dataclass(eq=False)
class TakeTracks:
    """Every frame's tracks: rows start[f]:start[f+1] belong to frame f, ids ascending."""

    start: np.ndarray  # (F + 1,)
    ids: np.ndarray  # (N,) int64
    xyz: np.ndarray  # (N, 3) metres: the point if seen, else the track's prediction
    seen: np.ndarray  # (N,) bool
    missing: np.ndarray  # (N,) frames since last seen

    def __len__(self) -> int:
        return len(self.start) - 1

    def tracks_at(self, f: int) -> TrackFrame:
        """Frame f's tracks as the live tracker hands them to the rigid tracker."""
        a, b = int(self.start[f]), int(self.start[f + 1])
        return TrackFrame(self.ids[a:b], self.xyz[a:b], self.seen[a:b],
                          self.seen[a:b].astype(np.int64), np.zeros((b - a, 0), np.int64),
                          self.missing[a:b])


@jit
def _grow(a, n):
    out = np.empty((max(2 * a.shape[0], n),) + a.shape[1:], a.dtype)
    out[:a.shape[0]] = a
    return out


@jit
def _associate(xyz, counts, frames, gate_m, max_missing, alpha, ids, pos, vel, miss,
               n_live, next_id, last):
    n_frames, width = xyz.shape[0], xyz.shape[1]
    cap = max(width * (max_missing + 2) + 16, n_live + 16)
    if ids.shape[0] < cap:  # the live tracks carried in, with room for this window's
        ids, pos, vel, miss = _grow(ids, cap), _grow(pos, cap), _grow(vel, cap), \
            _grow(miss, cap)
    cap = ids.shape[0]
    out_n = 0
    out_cap = max(16, n_frames * width * 2)
    o_ids = np.zeros(out_cap, np.int64)
    o_xyz = np.zeros((out_cap, 3))
    o_seen = np.zeros(out_cap, np.bool_)
    o_miss = np.zeros(out_cap, np.int64)
    start = np.zeros(n_frames + 1, np.int64)
    pred = np.zeros((cap, 3))
    d2 = np.zeros((cap, width))
    near_p = np.zeros(cap, np.int64)
    near_t = np.zeros(width, np.int64)
    pair_of_track = np.zeros(cap, np.int64)
    paired_point = np.zeros(width, np.bool_)
    for f in range(n_frames):
        step = max(frames[f] - last, 1)
        last = frames[f]
        n = counts[f]
        for j in range(n_live):
            s = miss[j] + step
            for c in range(3):
                pred[j, c] = pos[j, c] + vel[j, c] * s
        for i in range(n):
            near_t[i] = -1
            paired_point[i] = False
        for j in range(n_live):
            best, bi = np.inf, -1
            for i in range(n):
                d = 0.0
                for c in range(3):
                    e = pred[j, c] - xyz[f, i, c]
                    d += e * e
                d2[j, i] = d
                if d < best:
                    best, bi = d, i
            near_p[j] = bi
        for i in range(n):
            best, bj = np.inf, -1
            for j in range(n_live):
                if d2[j, i] < best:
                    best, bj = d2[j, i], j
            near_t[i] = bj
        gate2 = gate_m * gate_m
        for j in range(n_live):
            i = near_p[j]
            pair_of_track[j] = -1
            if i >= 0 and near_t[i] == j and d2[j, i] < gate2:
                pair_of_track[j] = i
                paired_point[i] = True
        # update, drop the stale, append the new (ids stay ascending)
        keep = 0
        need = n_live + n
        if out_n + need > o_ids.shape[0]:
            o_ids = _grow(o_ids, out_n + need)
            o_xyz = _grow(o_xyz, out_n + need)
            o_seen = _grow(o_seen, out_n + need)
            o_miss = _grow(o_miss, out_n + need)
        start[f] = out_n
        for j in range(n_live):
            i = pair_of_track[j]
            if i >= 0:
                s = miss[j] + step
                for c in range(3):
                    v = (xyz[f, i, c] - pos[j, c]) / s
                    vel[j, c] = alpha * v + (1 - alpha) * vel[j, c] if miss[j] == 0 else v
                    pos[j, c] = xyz[f, i, c]
                miss[j] = 0
            else:
                miss[j] += step
                if miss[j] > max_missing:
                    continue
            ids[keep] = ids[j]
            miss[keep] = miss[j]
            for c in range(3):
                pos[keep, c] = pos[j, c]
                vel[keep, c] = vel[j, c]
            o_ids[out_n] = ids[j]
            o_seen[out_n] = i >= 0
            o_miss[out_n] = miss[j]
            for c in range(3):
                o_xyz[out_n, c] = xyz[f, i, c] if i >= 0 else pred[j, c]
            out_n += 1
            keep += 1
        n_live = keep
        for i in range(n):
            if paired_point[i]:
                continue
            if n_live == ids.shape[0]:
                ids = _grow(ids, n_live + 1)
                pos = _grow(pos, n_live + 1)
                vel = _grow(vel, n_live + 1)
                miss = _grow(miss, n_live + 1)
                pred = _grow(pred, n_live + 1)
                d2 = _grow(d2, n_live + 1)
                near_p = _grow(near_p, n_live + 1)
                pair_of_track = _grow(pair_of_track, n_live + 1)
            ids[n_live] = next_id
            miss[n_live] = 0
            for c in range(3):
                pos[n_live, c] = xyz[f, i, c]
                vel[n_live, c] = 0.0
            o_ids[out_n] = next_id
            o_seen[out_n] = True
            o_miss[out_n] = 0
            for c in range(3):
                o_xyz[out_n, c] = xyz[f, i, c]
            out_n += 1
            n_live += 1
            next_id += 1
    start[n_frames] = out_n
    return start, o_ids[:out_n].copy(), o_xyz[:out_n].copy(), o_seen[:out_n].copy(), \
        o_miss[:out_n].copy(), ids, pos, vel, miss, n_live, next_id, last


class PointTracker:
    """The association resumable window by window: the live tracks (ids, positions,
    velocities, frames missing), the next id and the last frame number are carried from
    one window to the next, so a take tracked in windows gets the tracks of the whole take
    run at once, row for row, whatever the windows (nothing is re-tracked at an edge)."""

    def __init__(self, config: PointTrackConfig | None = None) -> None:
        self.config = config or PointTrackConfig()
        self.ids = np.zeros(0, np.int64)
        self.pos = np.zeros((0, 3))
        self.vel = np.zeros((0, 3))
        self.miss = np.zeros(0, np.int64)
        self.n_live = 0
        self.next_id = 1
        self.last = None  # the last frame number tracked

    def window(self, xyz: np.ndarray, counts: np.ndarray, frames: np.ndarray) -> TakeTracks:
        """The tracks of the next frames: xyz (F, P, 3) with frame f's counts[f] points
        first, frames (F,) their numbers, after the last window's (a gap is coasted over)."""
        cfg = self.config
        xyz = np.ascontiguousarray(xyz, dtype=np.float64)
        counts = np.ascontiguousarray(counts, dtype=np.int64)
        frames = np.ascontiguousarray(frames, dtype=np.int64)
        if not len(frames):
            return TakeTracks(np.zeros(1, np.int64), np.zeros(0, np.int64),
                              np.zeros((0, 3)), np.zeros(0, bool), np.zeros(0, np.int64))
        last = int(frames[0]) - 1 if self.last is None else self.last
        (start, ids, where, seen, missing, self.ids, self.pos, self.vel, self.miss,
         n_live, next_id, last) = _associate(
            xyz, counts, frames, float(cfg.gate_m), int(cfg.max_missing),
            float(cfg.velocity_alpha), self.ids, self.pos, self.vel, self.miss,
            int(self.n_live), int(self.next_id), int(last))
        self.n_live, self.next_id, self.last = int(n_live), int(next_id), int(last)
        return TakeTracks(start, ids, where, seen, missing)


def associate(xyz: np.ndarray, counts: np.ndarray, frames: np.ndarray,
              config: PointTrackConfig | None = None) -> TakeTracks:
    """Tracks of a whole take's points: xyz (F, P, 3) with frame f's counts[f] points
    first, frames (F,) the frame numbers (a gap in them is coasted over)."""
    return PointTracker(config).window(xyz, counts, frames)
