"""3D marker tracking with identities: predict, reproject, take the gated blob, triangulate.

Why tracks rather than matching every frame from scratch: the epipolar correspondence is
the slow, ambiguous step (ghosts, markers on one epipolar line). A marker seen last frame
is almost exactly where its constant-velocity prediction projects, so the nearest blob
within a few pixels in each camera is its blob, cheaply and without ambiguity; only the
blobs left over go to the correspondence, which finds new markers. A track that loses its
blobs coasts on its prediction for a few frames and takes them back, so an identity (and a
rigid body's marker assignment) survives short occlusions.

Close markers: two markers passing each other lie within each other's gates in many
cameras, and where their images overlap they give one blob at neither's place; a track that
took it would be pulled towards the other marker (and, as they part, could follow it: an
identity swap). So in each camera a track takes its nearest blob only when the pairing is
unambiguous both ways: every other blob in its gate, and every other track whose gate holds
the blob, at least `ambiguous_px` farther, and the blob no other track's nearest (one blob
nearest to two tracks is the two merged, or one of them hidden). Refusing every blob within
two gates instead threw away the cameras that do see the pair apart, and a track left with
two cameras that saw merged blobs was triangulated centimetres off, took a wrong velocity
from it and flew away, leaving its neighbour's track to take its blobs. With the blobs'
areas a blob larger than the track's own marker image at its predicted depth (each track
learns its marker's size) is not its own either. A track left without blobs is triangulated
from its other cameras, or coasts.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from calibkit.core.camera import Rig
from calibkit.core.geometry import RigArrays
from calibkit.vision.correspondence import CorrespondenceConfig, match_frame
from daemon.tracking.tracker_kernel import gate_and_solve


@dataclass(frozen=True)
class TrackerConfig:
    gate_px: float = 3.0  # a blob farther than this from a track's reprojection is not its own
    gate_growth_px: float = 1.0  # extra gate per frame a track has been missing (up to 4)
    max_missing: int = 24  # frames a track coasts on its prediction before it is dropped
    outlier_px: float = 2.0  # an observation whose residual exceeds this is dropped
    two_view_px: float = 1.0  # a point from two cameras must fit this well
    min_cameras_new: int = 3  # cameras needed to start a track (a pair is ambiguous)
    merge_m: float = 0.01  # a new point this close to a track is that track
    revive_m: float = 0.03  # a new point this close to a coasting track revives it
    velocity_alpha: float = 0.7  # weight of the newest velocity estimate
    new_tracks_every: int = 4  # look for new markers every N frames (every frame if none)
    # a blob larger than this times the track's marker image at its depth (plus the margin,
    # in px^2) is two markers merged, not the track's own; 0 turns the area test off
    merge_area_ratio: float = 1.4
    merge_margin_px2: float = 1.0
    # a track takes its nearest blob in a camera only if every other blob in its gate, and
    # every other track whose gate holds that blob, is at least this much farther (px):
    # two markers passing close keep the cameras that see them apart, and give up those
    # that cannot tell them apart (about four times the centroid noise of a good rig)
    ambiguous_px: float = 1.0
    # a point from two cameras is taken only if their rays meet at least this far from
    # parallel and from antiparallel (cameras facing each other across the volume): along
    # the rays such a point is determined only to (pixel error) / sin(angle), at 12 degrees
    # a centimetre for 0.2 px, and a track that took it would also take a wrong velocity
    min_two_view_deg: float = 25.0
    compiled: bool = True  # the numba kernel for gating and triangulation (else numpy)
    correspondence: CorrespondenceConfig = field(
        default_factory=lambda: CorrespondenceConfig(two_camera=False))


class AllCameras:
    """Projection of points into every camera of a rig at once, laid out (point, camera):
    one matrix product for all rotations, the distortion broadcast over cameras, no
    per-observation gathering. The tracker projects every track into every camera every
    frame, so this layout is what it needs."""

    def __init__(self, arrays: RigArrays) -> None:
        self.arrays = arrays
        self.n = len(arrays.fx)
        self.R_stack = arrays.R.reshape(-1, 3).T.copy()  # (3, 3C): X @ R_stack -> (T, 3C)
        self.R = arrays.R
        self.t = arrays.t.reshape(1, -1)  # (1, 3C)
        self.fx, self.fy, self.cx, self.cy, self.skew = (
            v[None, :] for v in (arrays.fx, arrays.fy, arrays.cx, arrays.cy, arrays.skew))
        self.k1, self.k2, self.p1, self.p2, self.k3 = (arrays.dist[:, i][None, :]
                                                       for i in range(5))

    def project(self, xyz: np.ndarray):
        """(T, 3) -> pixels (T, C, 2), depth (T, C), d pixels / d xyz (T, C, 2, 3)."""
        pc = (xyz @ self.R_stack + self.t).reshape(len(xyz), self.n, 3)
        z = pc[:, :, 2]
        zs = np.where(np.abs(z) < 1e-12, 1e-12, z)
        inv_z = 1.0 / zs
        x, y = pc[:, :, 0] * inv_z, pc[:, :, 1] * inv_z
        k1, k2, k3, p1, p2 = self.k1, self.k2, self.k3, self.p1, self.p2
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
        yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
        uv = np.empty(z.shape + (2,))
        uv[:, :, 0] = self.fx * xd + self.skew * yd + self.cx
        uv[:, :, 1] = self.fy * yd + self.cy
        dradial = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)
        j11 = radial + 2.0 * x * x * dradial + 2.0 * p1 * y + 6.0 * p2 * x
        j12 = 2.0 * x * y * dradial + 2.0 * p1 * x + 2.0 * p2 * y
        j22 = radial + 2.0 * y * y * dradial + 6.0 * p1 * y + 2.0 * p2 * x
        a11 = (self.fx * j11 + self.skew * j12) * inv_z
        a12 = (self.fx * j12 + self.skew * j22) * inv_z
        a21 = self.fy * j12 * inv_z
        a22 = self.fy * j22 * inv_z
        # d(uv)/d(pc) (T, C, 2, 3), then times R (C, 3, 3)
        Jc = np.empty(z.shape + (2, 3))
        Jc[:, :, 0, 0], Jc[:, :, 0, 1] = a11, a12
        Jc[:, :, 0, 2] = -(a11 * x + a12 * y)
        Jc[:, :, 1, 0], Jc[:, :, 1, 1] = a21, a22
        Jc[:, :, 1, 2] = -(a21 * x + a22 * y)
        return uv, z, np.matmul(Jc, self.R[None])


@dataclass(eq=False)
class TrackFrame:
    """The tracks after one frame, sorted by id."""

    ids: np.ndarray  # (T,) int64, stable identities
    xyz: np.ndarray  # (T, 3) metres; the prediction for tracks not seen this frame
    seen: np.ndarray  # (T,) bool: triangulated this frame
    n_cameras: np.ndarray  # (T,) observations used this frame
    blobs: np.ndarray  # (T, C) index of the frame's blob each camera gave, -1 if none
    missing: np.ndarray  # (T,) frames since last seen
    sigma_m: np.ndarray | None = None  # (T,) position std per pixel of noise (m/px)

    def __len__(self) -> int:
        return len(self.ids)


class Tracker:
    """Keeps 3D marker tracks across frames of one rig."""

    def __init__(self, rig: Rig, config: TrackerConfig | None = None) -> None:
        self.rig = rig
        self.config = config or TrackerConfig()
        self.arrays = RigArrays.from_rig(rig)
        self.cams = AllCameras(self.arrays)
        self.n_cameras = len(rig)
        self.sizes = np.array([c.size for c in rig], dtype=np.float64)  # (C, 2)
        self.centres = -np.einsum("cji,cj->ci", self.arrays.R, self.arrays.t)  # (C, 3)
        self.min_cos_two_view = float(np.cos(np.radians(self.config.min_two_view_deg)))
        self.ids = np.zeros(0, dtype=np.int64)
        self.xyz = np.zeros((0, 3))
        self.vel = np.zeros((0, 3))
        self.missing = np.zeros(0, dtype=np.int64)
        self.anchored = np.zeros(0, dtype=bool)  # placed by their rigid body since last frame
        self.size_m2 = np.zeros(0)  # each track's marker size: area x depth^2 / fx^2 (0: unknown)
        self.merged_blobs = 0  # blobs taken for merged by their area, since the start
        self.next_id = 1
        self.last_t_ns: int | None = None
        self.period_s: float | None = None  # the cameras' frame period, when known
        self.frames = 0

    def carry_tracks(self, old: Tracker) -> None:
        """Go on with another tracker's tracks, on the same rig (a reload that changed
        only the gates): ids, places, velocities and the frame clock carry over, so the
        bodies built on them stay identified through the swap."""
        for name in ("ids", "xyz", "vel", "missing", "anchored", "size_m2", "merged_blobs",
                     "next_id", "last_t_ns", "period_s", "frames"):
            setattr(self, name, getattr(old, name))

    def set_tracks(self, ids: np.ndarray, xyz: np.ndarray) -> None:
        """Start from these tracks (ids ascending), at rest and just seen: for warming the
        compiled kernels up and for tests; every per-track array stays the same length."""
        self.ids = np.asarray(ids, dtype=np.int64).reshape(-1).copy()
        n = len(self.ids)
        self.xyz = np.asarray(xyz, dtype=np.float64).reshape(n, 3).copy()
        self.vel = np.zeros((n, 3))
        self.missing = np.zeros(n, dtype=np.int64)
        self.anchored = np.zeros(n, dtype=bool)
        self.size_m2 = np.zeros(n)
        self.next_id = int(self.ids.max(initial=0)) + 1

    def place(self, ids: np.ndarray, xyz: np.ndarray) -> None:
        """Move coasting tracks to better positions (an occluded marker where its rigid
        body's pose puts it); their next prediction starts there. Such a track is
        "anchored" for the next frame: its prediction is as good as its body's pose, so its
        gate does not grow and only a point on top of it (merge_m) may revive it; a marker of
        another body passing through its place would otherwise take its identity."""
        if not len(ids) or not len(self.ids):
            return
        pos = np.minimum(np.searchsorted(self.ids, ids), len(self.ids) - 1)
        hit = self.ids[pos] == ids
        self.xyz[pos[hit]] = xyz[hit]
        self.anchored[pos[hit]] = True

    def reset(self) -> None:
        self.__init__(self.rig, self.config)

    # ---- one frame ---------------------------------------------------------------------

    def update(self, camera: np.ndarray, uv: np.ndarray, t_ns: int,
               area: np.ndarray | None = None) -> TrackFrame:
        """Blobs of one frame (camera index (M,), distorted pixels (M, 2), and their areas
        in pixels when the cameras give them) -> tracks."""
        cfg = self.config
        camera = np.asarray(camera, dtype=np.int64).reshape(-1)
        uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
        area = (np.zeros(0) if area is None or cfg.merge_area_ratio <= 0
                else np.asarray(area, dtype=np.float64).reshape(-1))
        if len(area) and len(area) != len(uv):
            raise ValueError(f"{len(area)} blob areas for {len(uv)} blobs")
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
        self.sigma = np.full(n_tracks, np.inf)
        if n_tracks and n_blobs and cfg.compiled:
            a = self.arrays
            order = np.argsort(camera, kind="stable")
            starts = np.searchsorted(camera[order], np.arange(n_cameras + 1))
            gate = self._gates()
            need = np.where(self.missing > 0, 3, 2)
            blobs, explained, xyz, ok, n_used, sigma, merged = gate_and_solve(
                pred, gate.astype(np.float64), need, a.R, a.t, a.fx, a.fy, a.cx, a.cy, a.skew,
                a.dist, order, starts, uv, cfg.outlier_px, cfg.two_view_px, area,
                self.size_m2, cfg.merge_area_ratio, cfg.merge_margin_px2, cfg.ambiguous_px,
                self.min_cos_two_view)
            self.merged_blobs += int(merged.sum())
            self.sigma = sigma
            seen = ok
            n_cams = n_used
            new_xyz[ok] = xyz[ok]
        elif n_tracks and n_blobs:
            proj, z, J = self.cams.project(pred)
            blobs, explained = self._associate(proj, z, camera, uv, area)
            ok, xyz, n_used, blobs = self._triangulate(pred, proj, J, uv, blobs)
            if len(area):
                self._learn_sizes(ok, blobs, z, area)
            seen = ok
            n_cams = n_used
            new_xyz[ok] = xyz[ok]
        if dt > 0 and np.any(seen):
            v = (new_xyz[seen] - self.xyz[seen]) / dt
            alpha = cfg.velocity_alpha
            if self.period_s and dt < self.period_s:
                # updates closer than a frame (the greedy multiplexer: a set per camera)
                # each move the velocity less: k of them together as much as one a frame
                # apart, so a 1 ms step's noise (noise / dt) does not throw the track off
                alpha = 1.0 - (1.0 - alpha) ** (dt / self.period_s)
            a = np.where(self.missing[seen] == 0, alpha, 1.0)[:, None]
            self.vel[seen] = a * v + (1 - a) * self.vel[seen]
        self.xyz = new_xyz
        self.missing = np.where(seen, 0, self.missing + 1)
        self.vel[~seen] *= 0.97  # a coasting track slows down rather than flying off
        blobs[~seen] = -1
        n_cams = np.where(seen, n_cams, 0)

        self.frames += 1
        used = explained.copy()
        used[blobs[blobs >= 0]] = True
        due = not np.any(seen) or self.frames % max(1, cfg.new_tracks_every) == 0
        if due and n_blobs - used.sum() >= cfg.min_cameras_new:
            blobs, seen, n_cams = self._new_tracks(camera, uv, used, blobs, seen, n_cams)
        keep = self.missing <= cfg.max_missing
        if len(self.ids) > n_tracks:  # new tracks this frame: check for duplicates
            keep &= self._not_duplicate(seen)
        if not np.all(keep):
            self.ids, self.xyz, self.vel = self.ids[keep], self.xyz[keep], self.vel[keep]
            self.missing = self.missing[keep]
            self.anchored = self.anchored[keep]
            self.size_m2 = self.size_m2[keep]
            blobs, seen, n_cams = blobs[keep], seen[keep], n_cams[keep]
            self.sigma = self.sigma[keep]
        self.anchored[:] = False  # until the rigid bodies place their hidden markers again
        sigma = np.where(seen, self.sigma, np.inf)
        return TrackFrame(self.ids.copy(), self.xyz.copy(), seen, n_cams, blobs,
                          self.missing.copy(), sigma)

    def _gates(self) -> np.ndarray:
        """Each track's gate (px): wider the longer it has been missing, unless its rigid
        body placed it."""
        cfg = self.config
        growth = np.where(self.anchored, 0, np.minimum(self.missing, 4))
        return cfg.gate_px + cfg.gate_growth_px * growth

    def _associate(self, proj: np.ndarray, z: np.ndarray, camera: np.ndarray,
                   uv: np.ndarray, area: np.ndarray):
        """(T, C) blob index per track and camera, and which blobs lie within some track's
        gate (explained: not a new marker). A track takes its nearest blob within the gate
        when the pairing is unambiguous both ways (see the module docstring): every other
        blob in its gate and every other track whose gate holds the blob at least
        ambiguous_px farther, the blob no other track's nearest, and not larger than the
        track's marker at its depth (a merged blob).

        proj (T, C, 2) and z (T, C) are the tracks' predictions in every camera. The
        blobs are padded into a (C, Mmax) table so all cameras are compared at once."""
        cfg = self.config
        front = z > 0
        n_tracks, n_cams = front.shape
        order = np.argsort(camera, kind="stable")
        cam_sorted = camera[order]
        starts = np.searchsorted(cam_sorted, np.arange(n_cams))
        rank = np.arange(len(order)) - starts[cam_sorted]
        width = max(int(rank.max(initial=-1)) + 1, 1)
        table = np.full((n_cams, width, 2), np.inf)
        table[cam_sorted, rank] = uv[order]
        index = np.full((n_cams, width), -1, dtype=np.int64)
        index[cam_sorted, rank] = order
        gate = self._gates()  # (T,)
        dx = proj[:, :, 0, None] - table[None, :, :, 0]
        dy = proj[:, :, 1, None] - table[None, :, :, 1]
        d2 = dx * dx + dy * dy  # (T, C, W)
        within = (d2 <= (gate * gate)[:, None, None]) & front[:, :, None]
        per_track = np.count_nonzero(within, axis=2)  # (T, C)
        per_blob = np.count_nonzero(within, axis=0)  # (C, W)
        d = np.where(within, np.sqrt(d2), np.inf)
        j = np.argmin(d, axis=2)  # (T, C)
        c = np.arange(n_cams)[None, :]
        t = np.arange(n_tracks)[:, None]
        d1 = d[t, c, j]
        second = (np.partition(d, 1, axis=2)[:, :, 1] if width > 1
                  else np.full(d1.shape, np.inf))
        # the blob's side: its nearest and second nearest track, and how many tracks it is
        # the nearest blob of
        bt1 = np.argmin(d, axis=0)  # (C, W)
        bd = np.sort(d, axis=0)[:2] if n_tracks > 1 else np.concatenate(
            [d, np.full(d.shape, np.inf)])
        has = np.isfinite(d1)
        nearest_of = np.zeros(n_cams * width, dtype=np.int64)
        np.add.at(nearest_of, (np.broadcast_to(c, j.shape) * width + j)[has], 1)
        nearest_of = nearest_of.reshape(n_cams, width)
        other = np.where(bt1[c, j] == t, bd[1][c, j], bd[0][c, j])
        d1 = np.where(has, d1, 0.0)
        good = (has & (nearest_of[c, j] == 1) & (second - d1 >= cfg.ambiguous_px)
                & (other - d1 >= cfg.ambiguous_px))
        out = np.where(good, index[c, j], -1)
        if len(area):
            expected = self.size_m2[:, None] * self.arrays.fx[None, :] ** 2 / np.where(
                front, z, 1.0) ** 2
            oversize = (per_track > 0) & (self.size_m2[:, None] > 0) & (
                area[np.maximum(index[c, j], 0)] > cfg.merge_area_ratio * expected
                + cfg.merge_margin_px2)
            self.merged_blobs += int(oversize.sum())
            out = np.where(oversize, -1, out)
        explained = np.zeros(len(uv), dtype=bool)
        hit = per_blob > 0
        explained[index[hit]] = True
        return out, explained

    def _learn_sizes(self, ok: np.ndarray, blobs: np.ndarray, z: np.ndarray,
                     area: np.ndarray) -> None:
        """Each triangulated track's marker size from this frame's blobs (the median over
        its cameras), folded in as daemon.tracking.tracker_kernel.learn_size does."""
        have = blobs >= 0
        size = np.where(have, area[np.maximum(blobs, 0)] * z * z
                        / self.arrays.fx[None, :] ** 2, np.nan)
        rows = np.flatnonzero(ok & have.any(axis=1))
        if not len(rows):
            return
        sample = np.nanmedian(size[rows], axis=1)
        cur = self.size_m2[rows]
        self.size_m2[rows] = np.where(cur <= 0, sample, np.exp(
            0.9 * np.log(np.maximum(cur, 1e-300)) + 0.1 * np.log(np.maximum(sample, 1e-30))))

    def _triangulate(self, pred, proj, J, uv, blobs):
        """Gauss-Newton in pixels, dense over (track, camera), linearised once at the
        prediction: the prediction is within millimetres, where the projection is linear
        to far below the noise, so the gating's projection and Jacobian serve for the
        solve too (no undistortion, no second projection). Observations whose linearised
        residual after the step exceeds outlier_px are dropped (the worst per track, while
        two others remain) and the step solved again.
        -> (ok (T,), xyz (T, 3), cameras used (T,), blobs with dropped ones set to -1)."""
        cfg = self.config
        n_tracks = len(blobs)
        have = blobs >= 0
        r = proj - uv[np.maximum(blobs, 0)]  # (T, C, 2)
        JtJ = np.matmul(J.transpose(0, 1, 3, 2), J)  # (T, C, 3, 3)
        Jtr = np.matmul(J.transpose(0, 1, 3, 2), r[..., None])[..., 0]  # (T, C, 3)
        t = np.arange(n_tracks)
        eye = np.eye(3) * 1e-9
        for it in range(2):
            w = have[:, :, None].astype(np.float64)
            H = np.sum(JtJ * w[..., None], axis=1) + eye
            g = np.sum(Jtr * w, axis=1)
            H_inv = np.linalg.inv(H)
            step = np.matmul(H_inv, g[:, :, None])[:, :, 0]
            r_after = r - np.matmul(J, step[:, None, :, None])[..., 0]
            e = np.where(have, np.sqrt(np.sum(r_after * r_after, axis=2)), -1.0)
            if it:
                break
            worst = np.argmax(e, axis=1)
            drop = (e[t, worst] > cfg.outlier_px) & (have.sum(axis=1) > 2)
            if not np.any(drop):
                break
            have[t[drop], worst[drop]] = False
        xyz = pred - step
        n_used = have.sum(axis=1)
        # Two rays always nearly meet when both blobs lie near one epipolar line, so a
        # two-camera point must fit tightly, and a track that was lost needs three cameras
        # to come back: otherwise a lost marker's track takes a passing neighbour.
        limit = np.where(n_used == 2, min(cfg.outlier_px, cfg.two_view_px), cfg.outlier_px)
        need = np.where(self.missing > 0, 3, 2)
        ok = (n_used >= need) & np.all(e <= limit[:, None], axis=1) & np.isfinite(xyz[:, 0])
        two = np.flatnonzero(ok & (n_used == 2))
        if len(two):  # the two rays must meet well away from parallel and antiparallel
            cams = np.argsort(~have[two], axis=1, kind="stable")[:, :2]  # (P, 2)
            ray = xyz[two][:, None, :] - self.centres[cams]  # (P, 2, 3)
            dot = np.sum(ray[:, 0] * ray[:, 1], axis=1)
            norms = np.sum(ray[:, 0] ** 2, axis=1) * np.sum(ray[:, 1] ** 2, axis=1)
            ok[two] = dot * dot < self.min_cos_two_view ** 2 * norms
        blobs = np.where(have, blobs, -1)
        # H^-1 is the point's covariance per unit pixel variance: a track seen by two
        # cameras at a narrow angle is far less certain (along its depth) than one seen by six
        self.sigma = np.sqrt(np.maximum(np.trace(H_inv, axis1=1, axis2=2), 0.0) / 3.0)
        return ok, xyz, n_used, blobs

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
            # a point near a coasting track is that track back, if each is the other's only
            # candidate (two markers near one lost track would swap identities)
            radius = np.where(self.anchored, cfg.merge_m, cfg.revive_m)
            close = ~seen[None, :] & (d < radius[None, :]) & take[:, None]
            near = np.argmax(close, axis=1)
            revive = (close.sum(axis=1) == 1) & (close.sum(axis=0)[near] == 1)
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
                self.sigma[tr] = np.where(np.isfinite(self.sigma[tr]), self.sigma[tr], 1e-3)
                take[revive] = False
        if np.any(take):
            k = int(take.sum())
            self.ids = np.concatenate([self.ids, np.arange(self.next_id, self.next_id + k)])
            self.next_id += k
            self.xyz = np.concatenate([self.xyz, xyz[take]])
            self.vel = np.concatenate([self.vel, np.zeros((k, 3))])
            self.missing = np.concatenate([self.missing, np.zeros(k, dtype=np.int64)])
            self.anchored = np.concatenate([self.anchored, np.zeros(k, dtype=bool)])
            self.size_m2 = np.concatenate([self.size_m2, np.zeros(k)])
            seen = np.concatenate([seen, np.ones(k, dtype=bool)])
            # a new point's certainty: like a tracked one seen by as many cameras
            typical = np.median(self.sigma[np.isfinite(self.sigma)]) if np.any(
                np.isfinite(self.sigma)) else 1e-3
            self.sigma = np.concatenate([self.sigma, np.full(k, typical)])
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
