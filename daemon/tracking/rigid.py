"""Rigid bodies: definitions, identification by inter-marker distances, pose, validity.

Why distances: they are the one property of a marker set that does not depend on its pose,
so a body is found among anonymous tracks by looking for tracks whose mutual distances
match its own. Once found, the body keeps its tracks (the tracker keeps their identities)
and is posed every frame by a weighted Kabsch fit, batched over all bodies. A marker
whose fit error grows is released (its track has swapped or merged); a body with too few
markers left is reported invalid, never frozen at its last pose.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from daemon.tracking.rigid_kernel import fit_bodies
from daemon.tracking.tracker import TrackFrame
from daemon.tracking.tracker_kernel import refine_step


@dataclass(frozen=True, eq=False)
class BodyDef:
    """One rigid body as the configuration defines it."""

    name: str
    id: int  # streaming id, 0..65535
    markers: np.ndarray  # (k, 3) metres, body frame
    pivot: np.ndarray  # (3,) the point reported as the body's position, body frame
    min_markers_start: int = 4  # (at most the marker count) four points fix a body uniquely
    min_markers_keep: int = 3
    smoothing: float = 0.0  # 0 = off; else weight of the previous pose (0..1)

    @property
    def distances(self) -> np.ndarray:
        m = self.markers
        return np.linalg.norm(m[:, None, :] - m[None, :, :], axis=2)


@dataclass(frozen=True)
class RigidConfig:
    distance_tol_m: float = 0.004  # a track pair matches a body's marker pair this closely
    max_error_m: float = 0.006  # a marker this far from its fitted place is released
    search_every: int = 1  # identify lost bodies every N frames (the search is the slow part)
    refine: bool = True  # refine each pose on the markers' 2D observations
    compiled: bool = True  # the refinement in the numba kernel (else numpy)


@dataclass(eq=False)
class BodyPoses:
    """Poses of every defined body for one frame, in definition order."""

    ids: np.ndarray  # (B,) streaming ids
    valid: np.ndarray  # (B,) bool
    position: np.ndarray  # (B, 3) metres, the pivot in the world (NaN when invalid)
    rotation: np.ndarray  # (B, 3, 3) body-to-world
    quaternion: np.ndarray  # (B, 4) x, y, z, w
    error_m: np.ndarray  # (B,) mean marker distance from its fitted place
    n_markers: np.ndarray  # (B,) markers used
    tracks: np.ndarray  # (B, K) track ids assigned to each body marker, -1 if none


def alike_bodies(bodies: list[BodyDef], tol_m: float) -> list[tuple[str, str]]:
    """Pairs of bodies with the same marker count whose distance sets differ by less than
    2 * tol_m: the identification cannot tell them apart."""
    out = []
    for i, a in enumerate(bodies):
        da = np.sort(a.distances[np.triu_indices(len(a.markers), 1)])
        for b in bodies[i + 1:]:
            if len(b.markers) != len(a.markers):
                continue
            db = np.sort(b.distances[np.triu_indices(len(b.markers), 1)])
            if np.max(np.abs(da - db)) < 2 * tol_m:
                out.append((a.name, b.name))
    return out


def quaternion_xyzw(R: np.ndarray) -> np.ndarray:
    """Rotation matrices (B, 3, 3) -> unit quaternions (B, 4) x, y, z, w with w >= 0."""
    R = np.asarray(R, dtype=np.float64).reshape(-1, 3, 3)
    m00, m11, m22 = R[:, 0, 0], R[:, 1, 1], R[:, 2, 2]
    q = np.empty((len(R), 4))
    q[:, 3] = np.sqrt(np.maximum(0.0, 1 + m00 + m11 + m22)) / 2
    q[:, 0] = np.sqrt(np.maximum(0.0, 1 + m00 - m11 - m22)) / 2
    q[:, 1] = np.sqrt(np.maximum(0.0, 1 - m00 + m11 - m22)) / 2
    q[:, 2] = np.sqrt(np.maximum(0.0, 1 - m00 - m11 + m22)) / 2
    q[:, 0] = np.copysign(q[:, 0], R[:, 2, 1] - R[:, 1, 2])
    q[:, 1] = np.copysign(q[:, 1], R[:, 0, 2] - R[:, 2, 0])
    q[:, 2] = np.copysign(q[:, 2], R[:, 1, 0] - R[:, 0, 1])
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def kabsch_batch(src: np.ndarray, dst: np.ndarray, w: np.ndarray):
    """Weighted rigid fits of B point sets at once: (R (B, 3, 3), t (B, 3)) minimising
    sum w |R src + t - dst|^2 per set, with the reflection fix. Sets with zero weight get
    the identity."""
    wsum = np.maximum(w.sum(axis=1, keepdims=True), 1e-12)
    wn = (w / wsum)[:, :, None]  # (B, K, 1)
    dst = np.where(wn > 0, dst, 0.0)
    mu_s = np.sum(wn * src, axis=1)
    mu_d = np.sum(wn * dst, axis=1)
    a = src - mu_s[:, None, :]
    b = (dst - mu_d[:, None, :]) * wn
    cov = np.matmul(b.transpose(0, 2, 1), a)  # (B, 3, 3)
    U, _, Vt = np.linalg.svd(cov)
    flip = np.linalg.det(np.matmul(U, Vt)) < 0
    U[flip, :, 2] *= -1.0
    R = np.matmul(U, Vt)
    t = mu_d - np.matmul(R, mu_s[:, :, None])[:, :, 0]
    return R, t


def _definition(b: BodyDef) -> tuple:
    """What makes two definitions the same body (a reload keeps such a body tracked)."""
    return (b.name, b.id, np.asarray(b.markers, np.float64).tobytes(),
            np.asarray(b.pivot, np.float64).tobytes(), b.min_markers_start,
            b.min_markers_keep, b.smoothing)


class RigidTracker:
    """Finds the defined bodies among the tracks and poses them every frame."""

    def __init__(self, bodies: list[BodyDef], config: RigidConfig | None = None) -> None:
        self.config = config or RigidConfig()
        self.frame = 0
        self.set_bodies(bodies)

    def seed(self, bodies: list[BodyDef], tracks: TrackFrame) -> dict[int, np.ndarray]:
        """Where each of a reload's bodies not defined before is among `tracks` (the last
        frame's): {index in bodies: track id per marker slot, -1 for none}. Run on the
        reload's thread and read-only here, so that the frame the swap happens in does not
        have to search for a new body (3-5 ms of the frame loop's time); set_bodies takes
        these as the new bodies' first assignment."""
        known = {_definition(b) for b in self.bodies}
        assigned = self.assigned.copy()
        taken = np.isin(tracks.ids, assigned[assigned >= 0])
        free = np.flatnonzero(tracks.seen & ~taken) if len(tracks) else np.zeros(0, np.int64)
        seeds: dict[int, np.ndarray] = {}
        for i, body in enumerate(bodies):
            if _definition(body) in known or len(free) < min(body.min_markers_start,
                                                                len(body.markers)):
                continue
            match = find_body(body, tracks.xyz[free], self.config.distance_tol_m,
                              self.config.max_error_m)
            if match is None:
                continue
            ids = np.full(len(body.markers), -1, dtype=np.int64)
            found = match >= 0
            ids[found] = tracks.ids[free[match[found]]]
            seeds[i] = ids
            free = np.setdiff1d(free, free[match[found]])
        return seeds

    def set_bodies(self, bodies: list[BodyDef], seeds: dict | None = None) -> None:
        """New definitions (a reload). A body defined exactly as before keeps its markers'
        tracks and last pose, so it stays tracked through the swap (adding a body does not
        make the others search again); a new or changed one is identified afresh."""
        old = {_definition(b): i for i, b in enumerate(getattr(self, "bodies", []))}
        kept = (self.assigned, self.prev_valid, self.prev_R, self.prev_t) if old else None
        self.bodies = list(bodies)
        n = len(self.bodies)
        k = max((len(b.markers) for b in self.bodies), default=1)
        self.k = k
        self.markers = np.zeros((n, k, 3))
        self.slot = np.zeros((n, k), dtype=bool)  # which marker slots exist
        for i, b in enumerate(self.bodies):
            self.markers[i, :len(b.markers)] = b.markers
            self.slot[i, :len(b.markers)] = True
        self.pivot = np.array([b.pivot for b in self.bodies]).reshape(n, 3)
        self.ids = np.array([b.id for b in self.bodies], dtype=np.int64)
        self.keep_min = np.array([b.min_markers_keep for b in self.bodies], dtype=np.int64)
        self.smoothing = np.array([b.smoothing for b in self.bodies], dtype=np.float64)
        self.assigned = np.full((n, k), -1, dtype=np.int64)  # track id per marker slot
        self.prev_valid = np.zeros(n, dtype=bool)
        self.prev_R = np.tile(np.eye(3), (n, 1, 1))
        self.prev_t = np.zeros((n, 3))
        for i, b in enumerate(self.bodies):
            j = old.get(_definition(b))
            if j is not None:
                m = len(b.markers)
                self.assigned[i, :m] = kept[0][j, :m]
                self.prev_valid[i], self.prev_R[i], self.prev_t[i] = (kept[1][j], kept[2][j],
                                                                     kept[3][j])
        held = self.assigned[self.assigned >= 0]
        for i, ids in (seeds or {}).items():  # found by seed(): no track taken twice
            if i < n and (self.assigned[i] < 0).all() and not np.isin(ids, held).any():
                self.assigned[i, :len(ids)] = ids
                held = np.concatenate([held, ids[ids >= 0]])
        # the last fit belongs to the old definitions: its shapes no longer match
        self._last = (None, None, None)
        self._last_rows = None  # (tracks, their rows per marker slot) of the last update

    def update(self, tracks: TrackFrame, uv: np.ndarray | None = None,
               cameras=None) -> BodyPoses:
        """Pose every body from the frame's tracks. With the frame's blobs `uv` and the
        tracker's all-camera projection `cameras` (daemon.tracking.tracker.AllCameras), each valid
        pose is then refined on the markers' 2D observations (see refine_poses)."""
        cfg = self.config
        self.frame += 1
        n = len(self.bodies)
        if n == 0:
            return BodyPoses(self.ids, np.zeros(0, bool), np.zeros((0, 3)), np.zeros((0, 3, 3)),
                             np.zeros((0, 4)), np.zeros(0), np.zeros(0, np.int64),
                             np.zeros((0, self.k), np.int64))
        # tracks that no longer exist release their slots
        row = self._rows(tracks, self.assigned)
        self.assigned[row < 0] = -1
        R, t, err, valid, used = self._fit(tracks, row)
        # a fit only releases slots (id -> -1): the rows of the rest stand, so they are
        # not searched for again (issue 33: _rows ran five times a frame)
        row = np.where(self.assigned >= 0, row, -1)
        before = self.assigned.copy()
        self._extend(tracks, R, t, valid)
        if (~valid).any() and self.frame % cfg.search_every == 0:
            self._identify(tracks, ~valid)
        if not np.array_equal(before, self.assigned):
            row = self._rows(tracks, self.assigned)
            R, t, err, valid, used = self._fit(tracks, row)
            row = np.where(self.assigned >= 0, row, -1)
        self._last_rows = (tracks, row)  # what hidden_markers needs, for these tracks
        if uv is not None and cameras is not None and cfg.refine and np.any(valid):
            obs = np.where((row >= 0)[..., None] & self._seen[..., None],
                           tracks.blobs[np.maximum(row, 0)], -1)  # (B, K, C)
            if cfg.compiled:
                a = cameras.arrays
                R, t = R.copy(), t.copy()
                refine_step(R, t, self.markers, obs, uv, a.R, a.t, a.fx, a.fy, a.cx, a.cy,
                            a.skew, a.dist, valid)
            else:
                R, t = refine_poses(R, t, self.markers, obs, uv, cameras, valid)
        self._last = (R, t, valid)
        R, t = self._smooth(R, t, valid)
        position = np.einsum("bij,bj->bi", R, self.pivot) + t
        position[~valid] = np.nan
        q = quaternion_xyzw(R)
        q[~valid] = np.nan
        err = np.where(valid, err, np.nan)
        return BodyPoses(self.ids.copy(), valid, position, R, q, err, used,
                         self.assigned.copy())

    def hidden_markers(self, tracks: TrackFrame) -> tuple[np.ndarray, np.ndarray]:
        """(track ids, positions) of the markers of tracked bodies whose tracks were not
        seen this frame: where the body's pose puts them. Handed back to the tracker, an
        occluded marker's track follows its body instead of coasting straight on, so it
        reappears inside its gate and a passing marker is not taken for it."""
        R, t, valid = self._last
        if R is None or not np.any(valid) or not len(tracks):
            return np.zeros(0, np.int64), np.zeros((0, 3))
        last = self._last_rows
        row = last[1] if last is not None and last[0] is tracks else self._rows(
            tracks, self.assigned)
        hidden = valid[:, None] & (row >= 0) & ~tracks.seen[np.maximum(row, 0)]
        b, k = np.nonzero(hidden)
        where = np.einsum("nij,nj->ni", R[b], self.markers[b, k]) + t[b]
        return self.assigned[b, k], where

    # ---- pieces ----------------------------------------------------------------------------

    @staticmethod
    def _rows(tracks: TrackFrame, track_ids: np.ndarray) -> np.ndarray:
        """Rows of `tracks` holding the given ids; -1 for ids gone (or -1)."""
        if not len(tracks):
            return np.full(track_ids.shape, -1, dtype=np.int64)
        pos = np.searchsorted(tracks.ids, track_ids)
        pos = np.minimum(pos, len(tracks) - 1)
        return np.where((track_ids >= 0) & (tracks.ids[pos] == track_ids), pos, -1)

    def _fit(self, tracks: TrackFrame, row: np.ndarray):
        """Fit every body to its seen markers, release markers that do not fit, refit."""
        cfg = self.config
        seen = np.zeros(row.shape, dtype=bool)
        if len(tracks):
            seen = (row >= 0) & tracks.seen[np.maximum(row, 0)]
        dst = tracks.xyz[np.maximum(row, 0)] if len(tracks) else np.zeros(row.shape + (3,))
        sigma = None
        if len(tracks) and tracks.sigma_m is not None:
            sigma = tracks.sigma_m[np.maximum(row, 0)]
        if cfg.compiled:
            use_sigma = sigma is not None
            R, t, err, seen, released = fit_bodies(
                self.markers, dst, seen, sigma if use_sigma else np.zeros(seen.shape),
                use_sigma, cfg.max_error_m, 3)
            self.assigned[released] = -1
        else:
            R, t, err = self._fit_numpy(dst, seen, sigma)  # releases in place
        count = seen.sum(axis=1)
        valid = count >= np.maximum(self.keep_min, 3)
        self._seen = seen
        return R, t, err, valid, count

    def _fit_numpy(self, dst, seen, sigma):
        """The numpy form of daemon.tracking.rigid_kernel.fit_bodies (the reference its tests use):
        fit, release the worst marker of each body that has one too far, fit again."""
        cfg = self.config
        for _ in range(3):
            # weights: inverse variance of each marker's triangulation, when known
            w = seen.astype(np.float64)
            if sigma is not None:
                w = np.where(seen, 1.0 / np.maximum(np.where(seen, sigma, 1.0), 1e-6) ** 2, 0.0)
            R, t = kabsch_batch(self.markers, dst, w)
            fitted = np.matmul(self.markers, R.transpose(0, 2, 1)) + t[:, None, :]
            diff = fitted - dst
            e = np.sqrt(np.sum(diff * diff, axis=2))
            count = seen.sum(axis=1)
            err = np.sum(np.where(seen, e, 0.0), axis=1) / np.maximum(count, 1)
            bad = seen & (e > cfg.max_error_m)
            if not np.any(bad):
                break
            # release the worst marker of each body that has one
            worst = np.argmax(np.where(bad, e, -1.0), axis=1)
            has = bad.any(axis=1)
            b = np.flatnonzero(has)
            self.assigned[b, worst[has]] = -1
            seen[b, worst[has]] = False
        return R, t, err

    def _extend(self, tracks: TrackFrame, R, t, valid) -> None:
        """Give free marker slots of tracked bodies the seen, unassigned track where the
        body's pose puts that marker."""
        if not len(tracks) or not np.any(valid):
            return
        free_slot = valid[:, None] & self.slot & (self.assigned < 0)
        if not np.any(free_slot):
            return
        taken = np.isin(tracks.ids, self.assigned[self.assigned >= 0])
        cand = np.flatnonzero(tracks.seen & ~taken)
        if not len(cand):
            return
        b, k = np.nonzero(free_slot)
        where = np.einsum("nij,nj->ni", R[b], self.markers[b, k]) + t[b]
        d = np.linalg.norm(where[:, None, :] - tracks.xyz[cand][None], axis=2)
        near = d < self.config.max_error_m
        j = np.argmin(np.where(near, d, np.inf), axis=1)
        ok = (near.sum(axis=1) == 1) & (near.sum(axis=0)[j] == 1)
        self.assigned[b[ok], k[ok]] = tracks.ids[cand[j[ok]]]

    def _identify(self, tracks: TrackFrame, lost: np.ndarray) -> None:
        """Search the free seen tracks for each lost body's distance pattern."""
        taken = np.isin(tracks.ids, self.assigned[self.assigned >= 0])
        free = np.flatnonzero(tracks.seen & ~taken) if len(tracks) else np.zeros(0, np.int64)
        for b in np.flatnonzero(lost):
            body = self.bodies[b]
            own = self._rows(tracks, self.assigned[b])
            own = own[own >= 0]
            pool = np.concatenate([free, own[tracks.seen[own]]])
            if len(pool) < min(body.min_markers_start, len(body.markers)):
                continue
            match = find_body(body, tracks.xyz[pool], self.config.distance_tol_m,
                              self.config.max_error_m)
            if match is None:
                continue  # keep the old assignment: its coasting tracks may come back
            slots = np.flatnonzero(match >= 0)
            self.assigned[b] = -1
            self.assigned[b, slots] = tracks.ids[pool[match[slots]]]
            free = np.setdiff1d(free, pool[match[slots]])

    def _smooth(self, R, t, valid):
        s = self.smoothing
        on = valid & self.prev_valid & (s > 0)
        if np.any(on):
            a = s[on][:, None]
            t = t.copy()
            t[on] = a * self.prev_t[on] + (1 - a) * t[on]
            q_new = quaternion_xyzw(R[on])
            q_old = quaternion_xyzw(self.prev_R[on])
            q_old *= np.sign(np.sum(q_old * q_new, axis=1, keepdims=True) + 1e-12)
            q = a * q_old + (1 - a) * q_new
            q /= np.linalg.norm(q, axis=1, keepdims=True)
            R = R.copy()
            R[on] = matrix_from_quaternion(q)
        self.prev_valid = valid.copy()
        self.prev_R = R.copy()
        self.prev_t = t.copy()
        return R, t


def _skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrices of vectors (..., 3) -> (..., 3, 3)."""
    S = np.zeros(v.shape + (3,))
    S[..., 0, 1], S[..., 0, 2] = -v[..., 2], v[..., 1]
    S[..., 1, 0], S[..., 1, 2] = v[..., 2], -v[..., 0]
    S[..., 2, 0], S[..., 2, 1] = -v[..., 1], v[..., 0]
    return S


def refine_poses(R, t, markers, obs, uv, cameras, valid, iterations: int = 1):
    """Gauss-Newton on each body's pose against the 2D blobs of its markers, batched over
    bodies: the maximum-likelihood pose under pixel noise.

    Why, after Kabsch: a triangulated marker's error is far from isotropic (long along the
    depth of the cameras that see it), and three or four markers of a small body give its
    orientation from those errors; fitting the pose to the pixels directly weighs every
    observation as the noise does. Starting from the Kabsch pose (within a millimetre),
    one step converges. obs (B, K, C): blob index per marker and camera, -1 if none.
    """
    B, K = markers.shape[:2]
    for _ in range(iterations):
        Rm = np.matmul(markers, R.transpose(0, 2, 1))  # (B, K, 3)
        X = Rm + t[:, None, :]
        proj, z, J = cameras.project(X.reshape(-1, 3))  # (BK, C, 2), (BK, C, 2, 3)
        C = proj.shape[1]
        have = (obs >= 0) & valid[:, None, None] & (z.reshape(B, K, C) > 0)
        r = proj.reshape(B, K, C, 2) - uv[np.maximum(obs, 0)]
        # dX / d(rotation increment, translation): [-[Rm]x | I]
        dX = np.concatenate([-_skew(Rm), np.broadcast_to(np.eye(3), (B, K, 3, 3))], axis=3)
        Jp = np.matmul(J.reshape(B, K, C, 2, 3), dX[:, :, None])  # (B, K, C, 2, 6)
        w = have[..., None, None].astype(np.float64)
        Jt = Jp.transpose(0, 1, 2, 4, 3)
        H = np.sum(np.matmul(Jt, Jp * w), axis=(1, 2))  # (B, 6, 6)
        g = np.sum(np.matmul(Jt, r[..., None] * w)[..., 0], axis=(1, 2))  # (B, 6)
        ok = valid & (have.sum(axis=(1, 2)) >= 6)
        if not np.any(ok):
            return R, t
        H[~ok] = np.eye(6)
        g[~ok] = 0.0
        step = -np.linalg.solve(H, g[:, :, None])[:, :, 0]
        theta = step[:, :3]
        angle = np.linalg.norm(theta, axis=1)
        axis = theta / np.maximum(angle, 1e-300)[:, None]
        Kx = _skew(axis)
        dR = (np.eye(3) + np.sin(angle)[:, None, None] * Kx
              + (1 - np.cos(angle))[:, None, None] * np.matmul(Kx, Kx))
        R = np.matmul(dR, R)
        t = t + step[:, 3:]
    return R, t


def matrix_from_quaternion(q: np.ndarray) -> np.ndarray:
    """Unit quaternions (B, 4) x, y, z, w -> rotation matrices (B, 3, 3)."""
    x, y, z, w = np.asarray(q, dtype=np.float64).reshape(-1, 4).T
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
        np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
        np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
    ], axis=1)


def find_body(body: BodyDef, xyz: np.ndarray, tol_m: float, max_error_m: float):
    """The assignment of points `xyz` (N, 3) to the body's markers that matches its
    distances: (k,) index into xyz or -1 for a marker not found; None if no assignment
    with at least min_markers_start markers fits within max_error_m.

    A depth-first search over the body's markers; each candidate set is the points whose
    distances to every point already chosen match the body's, so the branching collapses
    after the first two markers.
    """
    k = len(body.markers)
    n = len(xyz)
    need = max(3, min(body.min_markers_start, k))
    if n < need:
        return None
    D = np.linalg.norm(xyz[:, None, :] - xyz[None, :, :], axis=2)
    bd = body.distances
    compat = np.abs(D[None, None] - bd[:, :, None, None]) < tol_m  # (k, k, n, n)
    best, best_err = None, np.inf
    max_skip = k - need
    results: list[np.ndarray] = []
    choice = np.full(k, -1, dtype=np.int64)

    def search(i: int, skipped: int) -> None:
        if len(results) > 64:
            return
        if i == k:
            if k - skipped >= need:
                results.append(choice.copy())
            return
        mask = np.ones(n, dtype=bool)
        for j in range(i):
            if choice[j] >= 0:
                mask &= compat[j, i, choice[j]]
        mask[choice[:i][choice[:i] >= 0]] = False
        for c in np.flatnonzero(mask):
            choice[i] = c
            search(i + 1, skipped)
        choice[i] = -1
        if skipped < max_skip:
            search(i + 1, skipped + 1)

    search(0, 0)
    for r in results:
        sel = r >= 0
        R, t = kabsch_batch(body.markers[sel][None], xyz[r[sel]][None],
                            np.ones((1, int(sel.sum()))))
        fitted = body.markers[sel] @ R[0].T + t[0]
        e = np.linalg.norm(fitted - xyz[r[sel]], axis=1)
        # more markers first, then the smaller error
        score = (k - sel.sum()) * 1.0 + float(np.sqrt(np.mean(e**2)))
        if e.max() <= max_error_m and score < best_err:
            best, best_err = r, score
    return best
