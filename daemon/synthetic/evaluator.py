"""Scoring the daemon's rigid bodies against the simulator: pose errors and identity swaps."""

from __future__ import annotations

import numpy as np

from daemon.rigid import matrix_from_quaternion
from daemon.synthetic.scene import SimScene


class Evaluator:
    """Pose errors of the daemon's rigid bodies against the simulator, and identity swaps.

    A track's identity is the true marker most of its blobs came from this frame; a track
    swap is a track whose identity changes. A body swap is a valid body holding a track of
    another marker than its own (checked when the daemon's bodies are the scene's, marker
    for marker: `slots=True`). Poses more than 2 cm or 5 degrees off are counted apart as
    gross errors (a body posed from three close markers seen by few cameras can be that
    far off without any swap); they are left out of the RMS figures and reported.

    It runs on the frame loop, so it is vectorised over the bodies and keeps running sums
    only: its time is added to every frame's (a per-body loop here cost 1.2 ms a frame,
    more than the tracker, and delayed the next frame's pickup).
    """

    def __init__(self, scene: SimScene, skip_frames: int = 5, slots: bool = True) -> None:
        self.scene = scene
        self.skip = skip_frames
        self.slots = slots
        truth = scene.bodies_truth
        nb = len(truth)
        self.ids = np.array([b.id for b in truth], dtype=np.int64)
        k = max((len(b.marker_ids) for b in truth), default=0)
        self.marker_ids = np.full((nb, k), -1, dtype=np.int64)
        for i, b in enumerate(truth):
            self.marker_ids[i, :len(b.marker_ids)] = b.marker_ids
        self.poses = np.stack([b.poses for b in truth]) if nb else np.zeros((0, 1, 4, 4))
        self._quats = None  # (bodies, frames, 4) x y z w, made when first needed
        self.valid = np.zeros(nb, dtype=np.int64)
        self.gross = np.zeros(nb, dtype=np.int64)
        self.scored = np.zeros(nb, dtype=np.int64)  # valid frames within the gross limits
        self.pos_sq = np.zeros(nb)  # sums over scored frames, m^2 and deg^2
        self.ang_sq = np.zeros(nb)
        self.ang_max = np.zeros(nb)
        self.swapped = np.zeros(nb, dtype=bool)
        self.frames = 0
        self.last_label = np.full(1024, -1, dtype=np.int64)  # by track id; -1 never labelled
        self.track_swaps = 0
        self.body_swaps = 0

    def __call__(self, result) -> None:
        if result.scene_frame < 0:
            return
        self.frames += 1
        if self.frames <= self.skip:
            return
        labelled = self._tracks(result)
        p = result.poses
        if not len(self.ids) or not len(p.ids):
            return
        same = self.ids[:, None] == p.ids[None, :]  # (truth bodies, posed bodies)
        row = np.argmax(same, axis=1)
        ok = same.any(axis=1) & p.valid[row]
        if not ok.any():
            return
        if self.slots and labelled is not None:
            ids, labels = labelled
            k = min(p.tracks.shape[1], self.marker_ids.shape[1])
            tids = p.tracks[row, :k]
            if len(ids):
                at = np.minimum(np.searchsorted(ids, tids), len(ids) - 1)
                got = np.where((tids >= 0) & (ids[at] == tids), labels[at], -1)
            else:
                got = np.full(tids.shape, -1)
            want = self.marker_ids[:, :k]
            wrong = np.any((got >= 0) & (want >= 0) & (got != want), axis=1)
            self.body_swaps += int(np.sum(ok & wrong & ~self.swapped))
            self.swapped[ok] = wrong[ok]
        R_true, t_true = self._truth_at(result)
        e = np.linalg.norm(p.position[row] - t_true, axis=1)
        cos = (np.einsum("bij,bij->b", p.rotation[row], R_true) - 1) / 2
        a = np.degrees(np.arccos(np.clip(cos, -1, 1)))
        self.valid += ok
        gross = ok & ((e > 0.02) | (a > 5.0))
        self.gross += gross
        good = ok & ~gross
        self.scored += good
        self.pos_sq[good] += e[good] ** 2
        self.ang_sq[good] += a[good] ** 2
        self.ang_max[good] = np.maximum(self.ang_max[good], a[good])

    def _truth_at(self, result):
        """The bodies' true (R, t) when the frame set was taken. Live, a set's time may lie
        between two scene frames: unsynchronised cameras (the set's median capture time), or
        the greedy multiplexer (the newest camera's time, the others moved to it); the truth
        is then interpolated (positions linearly, orientations by normalised quaternions),
        as the simulator rendered each camera's view."""
        f = result.scene_frame
        T = self.poses[:, f]
        t0 = getattr(self.scene, "t0_ns", None)
        if t0 is None:  # not a live run: sets are taken at their frame's time
            return T[:, :3, :3], T[:, :3, 3]
        period = 1e9 / self.scene.fps
        at = f + (result.t_ns - t0 - result.frame * period) / period
        last = self.poses.shape[1] - 1
        if abs(at - f) < 1e-6 or last < 1:
            return T[:, :3, :3], T[:, :3, 3]
        base = int(min(max(np.floor(at), 0), last - 1))
        w = at - base
        if self._quats is None:
            from scipy.spatial.transform import Rotation

            R = self.poses[:, :, :3, :3]
            self._quats = Rotation.from_matrix(R.reshape(-1, 3, 3)).as_quat().reshape(
                R.shape[:2] + (4,))
        qa, qb = self._quats[:, base], self._quats[:, base + 1]
        qb = qb * np.sign(np.sum(qa * qb, axis=1, keepdims=True) + 1e-12)
        q = (1 - w) * qa + w * qb
        q /= np.linalg.norm(q, axis=1, keepdims=True)
        pos = (1 - w) * self.poses[:, base, :3, 3] + w * self.poses[:, base + 1, :3, 3]
        return matrix_from_quaternion(q), pos

    def _tracks(self, result):
        """This frame's track identities (track ids sorted, true markers); counts track
        swaps. None without the simulator's blob labels."""
        marker = result.blob_marker
        if marker is None:
            return None
        tb = result.tracks.blobs
        lab = np.where(tb >= 0, marker[np.maximum(tb, 0)], -1)  # (T, C)
        # the most frequent label of each row, vectorised: count equal entries per cell
        same = (lab[:, :, None] == lab[:, None, :]) & (lab[:, None, :] >= 0)
        votes = np.where(lab >= 0, same.sum(axis=2), 0)
        best = lab[np.arange(len(lab)), np.argmax(votes, axis=1)] if len(lab) else lab[:, 0]
        has = best >= 0
        ids, best = result.tracks.ids[has], best[has]
        if len(ids) and ids[-1] >= len(self.last_label):  # track ids only grow
            grown = np.full(max(2 * len(self.last_label), int(ids[-1]) + 1), -1, np.int64)
            grown[:len(self.last_label)] = self.last_label
            self.last_label = grown
        before = self.last_label[ids]
        self.track_swaps += int(np.sum((before >= 0) & (before != best)))
        self.last_label[ids] = best  # the latest label of every track ever labelled
        return ids, best

    def figures(self) -> dict:
        n = max(self.frames - self.skip, 1)
        bodies = {}
        for i, b in enumerate(self.scene.bodies_truth):
            m = self.scored[i]
            bodies[b.name] = {
                "id": b.id,
                "valid_fraction": int(self.valid[i]) / n,
                "gross_error_frames": int(self.gross[i]),
                "position_error_mm_rms": float(np.sqrt(self.pos_sq[i] / m) * 1000) if m
                else None,
                "orientation_error_deg_rms": float(np.sqrt(self.ang_sq[i] / m)) if m else None,
                "orientation_error_deg_max": float(self.ang_max[i]) if m else None,
            }
        m = int(self.scored.sum())
        return {
            "frames_scored": n,
            "bodies": bodies,
            "position_error_mm_rms": float(np.sqrt(self.pos_sq.sum() / m) * 1000) if m
            else None,
            "orientation_error_deg_rms": float(np.sqrt(self.ang_sq.sum() / m)) if m else None,
            "track_swaps": self.track_swaps,
            "body_swaps": self.body_swaps,
            "gross_error_frames": int(self.gross.sum()),
        }
