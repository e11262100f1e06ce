"""3D marker tracking with identities: predict, reproject, take the gated blob, triangulate.

Why tracks rather than matching every frame from scratch: the epipolar correspondence is
the slow, ambiguous step (ghosts, markers on one epipolar line). A marker seen last frame
is almost exactly where its constant-velocity prediction projects, so the nearest blob
within a few pixels in each camera is its blob, cheaply and without ambiguity; only the
blobs left over go to the correspondence, which finds new markers. A track that loses its
blobs coasts on its prediction for a few frames and takes them back, so an identity (and a
rigid body's marker assignment) survives short occlusions.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from calibkit.camera import Rig
from calibkit.correspondence import CorrespondenceConfig, match_frame
from calibkit.geometry import RigArrays


@dataclass(frozen=True)
class TrackerConfig:
    gate_px: float = 3.0  # a blob farther than this from a track's reprojection is not its own
    gate_growth_px: float = 2.0  # extra gate per frame a track has been missing
    max_missing: int = 24  # frames a track coasts on its prediction before it is dropped
    outlier_px: float = 2.0  # an observation whose residual exceeds this is dropped
    min_cameras_new: int = 3  # cameras needed to start a track (a pair is ambiguous)
    merge_m: float = 0.01  # a new point this close to a track is that track
    revive_m: float = 0.03  # a new point this close to a coasting track revives it
    velocity_alpha: float = 0.7  # weight of the newest velocity estimate
    new_tracks_every: int = 4  # look for new markers every N frames (every frame if none)
    correspondence: CorrespondenceConfig = field(
        default_factory=lambda: CorrespondenceConfig(two_camera=False))


@dataclass(eq=False)
class TrackFrame:
    """The tracks after one frame, sorted by id."""

    ids: np.ndarray  # (T,) int64, stable identities
    xyz: np.ndarray  # (T, 3) metres; the prediction for tracks not seen this frame
    seen: np.ndarray  # (T,) bool: triangulated this frame
    n_cameras: np.ndarray  # (T,) observations used this frame
    blobs: np.ndarray  # (T, C) index of the frame's blob each camera gave, -1 if none
    missing: np.ndarray  # (T,) frames since last seen

    def __len__(self) -> int:
        return len(self.ids)


class Tracker:
    """Keeps 3D marker tracks across frames of one rig."""

    def __init__(self, rig: Rig, config: TrackerConfig | None = None) -> None:
        self.rig = rig
        self.config = config or TrackerConfig()
        self.arrays = RigArrays.from_rig(rig)
        self.n_cameras = len(rig)
        self.sizes = np.array([c.size for c in rig], dtype=np.float64)  # (C, 2)
        self.ids = np.zeros(0, dtype=np.int64)
        self.xyz = np.zeros((0, 3))
        self.vel = np.zeros((0, 3))
        self.missing = np.zeros(0, dtype=np.int64)
        self.next_id = 1
        self.last_t_ns: int | None = None
        self.frames = 0
        self._cam_idx = np.zeros(0, dtype=np.int64)

    def reset(self) -> None:
        self.__init__(self.rig, self.config)

    # ---- one frame ---------------------------------------------------------------------

    def update(self, camera: np.ndarray, uv: np.ndarray, t_ns: int) -> TrackFrame:
        """Blobs of one frame (camera index (M,), distorted pixels (M, 2)) -> tracks."""
        cfg = self.config
        camera = np.asarray(camera, dtype=np.int64).reshape(-1)
        uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
        dt = 0.0 if self.last_t_ns is None else max(0.0, (t_ns - self.last_t_ns) * 1e-9)
        self.last_t_ns = int(t_ns)
        pred = self.xyz + self.vel * dt
        n_tracks, n_blobs = len(self.ids), len(uv)
        n_cameras = self.n_cameras
        blobs = np.full((n_tracks, n_cameras), -1, dtype=np.int64)
        explained = np.zeros(n_blobs, dtype=bool)
        seen = np.zeros(n_tracks, dtype=bool)
        n_cams = np.zeros(n_tracks, dtype=np.int64)
        new_xyz = pred.copy()
        if n_tracks and n_blobs:
            proj, z, J = self.arrays.project(self.cam_idx(n_tracks),
                                             np.repeat(pred, n_cameras, axis=0), jacobian=True)
            proj = proj.reshape(n_tracks, n_cameras, 2)
            blobs, explained = self._associate(proj, (z > 0).reshape(n_tracks, n_cameras),
                                               camera, uv)
            ok, xyz, n_used, blobs = self._triangulate(
                pred, proj, J.reshape(n_tracks, n_cameras, 2, 3), uv, blobs)
            seen = ok
            n_cams = n_used
            new_xyz[ok] = xyz[ok]
        if dt > 0 and np.any(seen):
            v = (new_xyz[seen] - self.xyz[seen]) / dt
            a = np.where(self.missing[seen] == 0, cfg.velocity_alpha, 1.0)[:, None]
            self.vel[seen] = a * v + (1 - a) * self.vel[seen]
        self.xyz = new_xyz
        self.missing = np.where(seen, 0, self.missing + 1)
        self.vel[~seen] *= 0.8  # a coasting track slows down rather than flying off
        blobs[~seen] = -1
        n_cams = np.where(seen, n_cams, 0)

        self.frames += 1
        used = explained.copy()
        used[blobs[blobs >= 0]] = True
        due = not np.any(seen) or self.frames % max(1, cfg.new_tracks_every) == 0
        if due and n_blobs - used.sum() >= cfg.min_cameras_new:
            blobs, seen, n_cams = self._new_tracks(camera, uv, used, blobs, seen, n_cams)
        keep = self.missing <= cfg.max_missing
        keep &= self._not_duplicate(seen)
        if not np.all(keep):
            self.ids, self.xyz, self.vel = self.ids[keep], self.xyz[keep], self.vel[keep]
            self.missing = self.missing[keep]
            blobs, seen, n_cams = blobs[keep], seen[keep], n_cams[keep]
        return TrackFrame(self.ids.copy(), self.xyz.copy(), seen, n_cams, blobs,
                          self.missing.copy())

    def _associate(self, proj: np.ndarray, front: np.ndarray, camera: np.ndarray,
                   uv: np.ndarray):
        """(T, C) blob index per track and camera: the only blob within the gate, and the
        track the only one whose reprojection falls within the gate of that blob; and which
        blobs lie within some track's gate (explained: not a new marker).

        proj (T, C, 2) and front (T, C) are the tracks' predictions in every camera. The
        blobs are padded into a (C, Mmax) table so all cameras are compared at once."""
        cfg = self.config
        n_tracks, n_cams = front.shape
        order = np.argsort(camera, kind="stable")
        cam_sorted = camera[order]
        starts = np.searchsorted(cam_sorted, np.arange(n_cams))
        rank = np.arange(len(order)) - starts[cam_sorted]
        width = int(rank.max(initial=-1)) + 1
        table = np.full((n_cams, max(width, 1), 2), np.inf)
        table[cam_sorted, rank] = uv[order]
        index = np.full((n_cams, max(width, 1)), -1, dtype=np.int64)
        index[cam_sorted, rank] = order
        gate = cfg.gate_px + cfg.gate_growth_px * np.minimum(self.missing, 5)  # (T,)
        dx = proj[:, :, 0, None] - table[None, :, :, 0]
        dy = proj[:, :, 1, None] - table[None, :, :, 1]
        d2 = dx * dx + dy * dy  # (T, C, W)
        within = (d2 <= (gate * gate)[:, None, None]) & front[:, :, None]
        per_track = np.count_nonzero(within, axis=2)  # (T, C)
        per_blob = np.count_nonzero(within, axis=0)  # (C, W)
        d2[~within] = np.inf
        j = np.argmin(d2, axis=2)  # (T, C)
        c = np.arange(n_cams)[None, :]
        good = (per_track == 1) & (per_blob[c, j] == 1)
        out = np.where(good, index[c, j], -1)
        explained = np.zeros(len(uv), dtype=bool)
        hit = per_blob > 0
        explained[index[hit]] = True
        return out, explained

    def _triangulate(self, pred, proj, J, uv, blobs):
        """Gauss-Newton in pixels from the prediction, dense over (track, camera): the
        prediction is within a millimetre, so no linear start (and no undistortion) is
        needed, and the prediction's projection and Jacobian (already computed for the
        gating) give the first step. An observation whose residual then exceeds outlier_px
        is dropped (the worst per track, while two others remain) before the second step.
        -> (ok (T,), xyz (T, 3), cameras used (T,), blobs with dropped ones set to -1)."""
        cfg = self.config
        n_tracks, n_cams = blobs.shape
        have = blobs >= 0
        obs = uv[np.maximum(blobs, 0)]  # (T, C, 2)
        xyz = pred.copy()
        t = np.arange(n_tracks)
        for it in range(2):
            if it:
                p, _, Jf = self.arrays.project(self.cam_idx(n_tracks),
                                               np.repeat(xyz, n_cams, axis=0), jacobian=True)
                proj, J = p.reshape(n_tracks, n_cams, 2), Jf.reshape(n_tracks, n_cams, 2, 3)
            r = proj - obs
            if it:  # after one step the residuals say which observations are wrong
                e = np.where(have, np.sqrt(np.sum(r * r, axis=2)), -1.0)
                worst = np.argmax(e, axis=1)
                drop = (e[t, worst] > cfg.outlier_px) & (have.sum(axis=1) > 2)
                have[t[drop], worst[drop]] = False
            w = have.astype(np.float64)
            H = np.einsum("tc,tcki,tckj->tij", w, J, J)
            g = np.einsum("tc,tcki,tck->ti", w, J, r)
            H += np.eye(3) * 1e-9
            step = np.linalg.solve(H, g[:, :, None])[:, :, 0]
            xyz -= step
        # residuals after the last step, to first order
        r_after = r - np.einsum("tckj,tj->tck", J, step)
        e = np.sqrt(np.sum(r_after * r_after, axis=2))
        n_used = have.sum(axis=1)
        ok = (n_used >= 2) & np.all(~have | (e <= cfg.outlier_px), axis=1)
        ok &= np.isfinite(xyz[:, 0])
        blobs = np.where(have, blobs, -1)
        return ok, xyz, n_used, blobs

    def cam_idx(self, n_tracks: int) -> np.ndarray:
        if len(self._cam_idx) < n_tracks * self.n_cameras:
            self._cam_idx = np.tile(np.arange(self.n_cameras), max(n_tracks, 64) * 2)
        return self._cam_idx[:n_tracks * self.n_cameras]

    def _new_tracks(self, camera, uv, used, blobs, seen, n_cams):
        cfg = self.config
        rest = np.flatnonzero(~used)
        if len(np.unique(camera[rest])) < cfg.min_cameras_new:
            return blobs, seen, n_cams
        found = match_frame(self.rig, camera[rest], uv[rest], cfg.correspondence)
        good = found.n_cameras >= cfg.min_cameras_new
        if not np.any(good):
            return blobs, seen, n_cams
        xyz = found.xyz[good]
        table = np.where(found.blobs[good] >= 0, rest[np.maximum(found.blobs[good], 0)], -1)
        ncam = found.n_cameras[good]
        take = np.ones(len(xyz), dtype=bool)
        if len(self.ids):
            d = np.linalg.norm(xyz[:, None, :] - self.xyz[None, :, :], axis=2)  # (P, T)
            # a point on top of a seen track is a duplicate of it
            take &= ~np.any((d < cfg.merge_m) & seen[None, :], axis=1)
            # a point near a coasting track is that track back
            coasting = np.where(~seen[None, :] & (d < cfg.revive_m), d, np.inf)
            near = np.argmin(coasting, axis=1)
            revive = take & np.isfinite(coasting[np.arange(len(xyz)), near])
            if np.any(revive):
                tr, pt = near[revive], np.flatnonzero(revive)
                tr, first = np.unique(tr, return_index=True)
                pt = pt[first]
                self.xyz[tr] = xyz[pt]
                self.vel[tr] = 0.0
                self.missing[tr] = 0
                seen[tr] = True
                blobs[tr] = table[pt]
                n_cams[tr] = ncam[pt]
                take[revive] = False
        if np.any(take):
            k = int(take.sum())
            self.ids = np.concatenate([self.ids, np.arange(self.next_id, self.next_id + k)])
            self.next_id += k
            self.xyz = np.concatenate([self.xyz, xyz[take]])
            self.vel = np.concatenate([self.vel, np.zeros((k, 3))])
            self.missing = np.concatenate([self.missing, np.zeros(k, dtype=np.int64)])
            seen = np.concatenate([seen, np.ones(k, dtype=bool)])
            n_cams = np.concatenate([n_cams, ncam[take]])
            blobs = np.concatenate([blobs, table[take]])
        return blobs, seen, n_cams

    def _not_duplicate(self, seen: np.ndarray) -> np.ndarray:
        """False for the younger of two seen tracks that have converged on one marker."""
        keep = np.ones(len(self.ids), dtype=bool)
        idx = np.flatnonzero(seen)
        if len(idx) < 2:
            return keep
        p = self.xyz[idx]
        d = np.linalg.norm(p[:, None, :] - p[None, :, :], axis=2)
        i, j = np.nonzero(np.triu(d < self.config.merge_m * 0.5, 1))
        keep[idx[j]] = False  # ids ascend with age, so j (the later one) is younger
        return keep
