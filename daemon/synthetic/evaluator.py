"""Scoring the daemon's rigid bodies against the simulator: pose errors, identity swaps, and
whether each frame set paired frames taken at the same instant."""

from __future__ import annotations

import numpy as np

from calibkit.core.geometry import rigid_fit
from daemon.synthetic.scene import SimScene

GROSS_M, GROSS_DEG = 0.02, 5.0  # a pose this far off is a gross error


class Evaluator:
    """Pose errors of the daemon's rigid bodies against the simulator, identity swaps, and
    frame sets that mix instants.

    The truth of each sample (which trigger it was, when it was taken, which marker each
    blob is) comes from the scene's ledger, found by the sample's camera and its own frame
    id and timestamp: nothing the daemon computes carries it. A set's poses are scored
    against the bodies where they were at the set's time (`t_ns`, the daemon's estimate of
    when it was taken), so a wrong time costs accuracy as it would on real cameras.

    Every valid pose counts in the RMS figures; those more than 2 cm or 5 degrees off are
    also counted as gross errors (a body posed from three close markers seen by few cameras
    can be that far off without any swap), and the RMS without them is given too, named so.
    A track's identity is the true marker most of its blobs came from this frame; a track
    swap is a track whose identity changes. A body swap is a valid body holding a track of
    another marker than its own (checked when the daemon's bodies are the scene's, marker
    for marker: `slots=True`). A set mixes instants when its cameras' true capture times
    are more than half a frame period apart (`check_instants`: triggered sets; greedy ones
    mix them by design, the extrapolation brings them together).

    It runs on the frame loop, so it is vectorised over the bodies and keeps running sums
    only: its time is added to every frame's (a per-body loop here cost 1.2 ms a frame,
    more than the tracker, and delayed the next frame's pickup).
    """

    def __init__(self, scene: SimScene, skip_frames: int = 5, slots: bool = True,
                 check_instants: bool = True, bodies=None) -> None:
        """`bodies`: the daemon's BodyDefs, matched to the scene's bodies by their shape
        (match_bodies); None: the daemon's bodies are the scene's, by id, marker for
        marker (a caller that made them so)."""
        self.scene = scene
        self.skip = skip_frames
        self.slots = slots
        self.check_instants = check_instants
        truth = scene.bodies_truth
        nb = len(truth)
        k = max((len(b.marker_ids) for b in truth), default=0)
        self.true_marker_ids = np.full((nb, k), -1, dtype=np.int64)
        for i, b in enumerate(truth):
            self.true_marker_ids[i, :len(b.marker_ids)] = b.marker_ids
        self.set_bodies(bodies)
        self.valid = np.zeros(nb, dtype=np.int64)
        self.gross = np.zeros(nb, dtype=np.int64)
        self.pos_sq = np.zeros(nb)  # sums over every valid pose, m^2 and deg^2
        self.ang_sq = np.zeros(nb)
        self.ang_max = np.zeros(nb)
        self.pos_sq_good = np.zeros(nb)  # the same over the poses within the gross limits
        self.ang_sq_good = np.zeros(nb)
        self.swapped = np.zeros(nb, dtype=bool)
        self.frames = 0
        self.last_label = np.full(1024, -1, dtype=np.int64)  # by track id; -1 never labelled
        self.track_swaps = 0
        self.body_swaps = 0
        self.sets_checked = 0  # sets whose every sample was found in the ledger
        self.mixed_sets = 0
        self.spread_max_ns = 0
        self.unknown_samples = 0  # samples the ledger no longer (or never) held

    def set_bodies(self, bodies) -> None:
        """Match the daemon's bodies to the scene's (at the start and after a reload)."""
        self.adopt(self.match(bodies))

    def match(self, bodies) -> dict:
        """Per scene body the daemon body's id (-1: none like it), the fixed transform from
        the scene body's frame to the daemon body's, and the true marker each of the daemon
        body's markers is (for the body-swap check). Reads only the scene's fixed truth, so
        a reload computes it on its own thread (milliseconds of fits) and the frame loop
        only `adopt`s it."""
        truth = self.scene.bodies_truth
        nb = len(truth)
        m = {"ids": np.full(nb, -1, dtype=np.int64), "R_off": np.tile(np.eye(3), (nb, 1, 1)),
             "t_off": np.zeros((nb, 3)), "marker_ids": self.true_marker_ids.copy(),
             "definition_mm": [None] * nb, "defined_as": [None] * nb}
        if bodies is None:
            m["ids"][:] = [b.id for b in truth]
            return m
        width = m["marker_ids"].shape[1]
        for i, j, perm, R, t, rms in match_bodies([b.markers_body for b in truth],
                                                  [b.markers for b in bodies]):
            m["ids"][i] = bodies[j].id
            m["R_off"][i], m["t_off"][i] = R, t
            m["definition_mm"][i] = rms * 1000
            m["defined_as"][i] = bodies[j].name
            row = np.full(width, -1, dtype=np.int64)
            slot = np.empty(len(perm), dtype=np.int64)
            slot[perm] = np.arange(len(perm))  # daemon marker perm[m] is true marker m
            k = min(len(slot), width)
            row[:k] = np.asarray(truth[i].marker_ids)[slot][:k]
            m["marker_ids"][i] = row
        return m

    def adopt(self, matched: dict) -> None:
        """Score against a `match` from here on (quick: assignments only)."""
        for name, value in matched.items():
            setattr(self, name, value)

    def __call__(self, result) -> None:
        samples = result.samples
        if not samples:
            return
        taken, marker = self.scene.truth_of(samples)
        self._instants(taken)
        self.frames += 1
        if self.frames <= self.skip:
            return
        labelled = self._tracks(result, marker)
        p = result.poses
        if not len(self.ids) or not len(p.ids):
            return
        same = (self.ids[:, None] == p.ids[None, :]) & (self.ids[:, None] >= 0)
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
        R_true, t_true = self.scene.body_poses_at(result.t_ns)
        R_est = p.rotation[row]  # the daemon's pose of the scene body's frame
        t_est = np.einsum("bij,bj->bi", R_est, self.t_off) + p.position[row]
        R_est = R_est @ self.R_off
        e = np.linalg.norm(t_est - t_true, axis=1)
        cos = (np.einsum("bij,bij->b", R_est, R_true) - 1) / 2
        a = np.degrees(np.arccos(np.clip(cos, -1, 1)))
        self.valid += ok
        self.pos_sq[ok] += e[ok] ** 2
        self.ang_sq[ok] += a[ok] ** 2
        self.ang_max[ok] = np.maximum(self.ang_max[ok], a[ok])
        gross = ok & ((e > GROSS_M) | (a > GROSS_DEG))
        self.gross += gross
        good = ok & ~gross
        self.pos_sq_good[good] += e[good] ** 2
        self.ang_sq_good[good] += a[good] ** 2

    def _instants(self, taken) -> None:
        """Whether the set's samples were really taken within half a frame period."""
        if not self.check_instants:
            return
        known = [t for t in taken if t is not None]
        self.unknown_samples += len(taken) - len(known)
        if len(known) < len(taken) or not known:
            return
        spread = max(known) - min(known)
        self.sets_checked += 1
        self.spread_max_ns = max(self.spread_max_ns, spread)
        if spread > 0.5e9 / self.scene.fps:
            self.mixed_sets += 1

    def _tracks(self, result, marker):
        """This frame's track identities (track ids sorted, true markers); counts track
        swaps. `marker`: the blobs' true markers from the ledger, sample by sample, in the
        order the pipeline concatenated them."""
        if len(marker) != len(result.uv):
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

        def rms(total, count, scale=1.0):
            return float(np.sqrt(total / count) * scale) if count else None

        bodies = {}
        good_n = self.valid - self.gross
        for i, b in enumerate(self.scene.bodies_truth):
            m, g = int(self.valid[i]), int(good_n[i])
            bodies[b.name] = {
                "id": b.id,
                "defined_as": self.defined_as[i],
                "definition_error_mm_rms": self.definition_mm[i],
                "valid_fraction": m / n,
                "position_error_mm_rms": rms(self.pos_sq[i], m, 1000),
                "orientation_error_deg_rms": rms(self.ang_sq[i], m),
                "orientation_error_deg_max": float(self.ang_max[i]) if m else None,
                "gross_error_frames": int(self.gross[i]),
                "position_error_mm_rms_without_gross": rms(self.pos_sq_good[i], g, 1000),
                "orientation_error_deg_rms_without_gross": rms(self.ang_sq_good[i], g),
            }
        m, g = int(self.valid.sum()), int(good_n.sum())
        return {
            "frames_scored": n,
            "bodies": bodies,
            "valid_poses": m,
            "position_error_mm_rms": rms(self.pos_sq.sum(), m, 1000),
            "orientation_error_deg_rms": rms(self.ang_sq.sum(), m),
            "gross_error_frames": int(self.gross.sum()),
            "position_error_mm_rms_without_gross": rms(self.pos_sq_good.sum(), g, 1000),
            "orientation_error_deg_rms_without_gross": rms(self.ang_sq_good.sum(), g),
            "track_swaps": self.track_swaps,
            "body_swaps": self.body_swaps,
            "sets_mixing_instants": self.mixed_sets if self.check_instants else None,
            "sets_checked_for_instants": self.sets_checked if self.check_instants else None,
            "set_instant_spread_ms_max": self.spread_max_ns * 1e-6 if self.check_instants
            else None,
            "samples_not_in_ledger": self.unknown_samples,
            "scene_t0_ns": int(self.scene.t0_ns),
        }


MATCH_RMS_M = 0.005  # a daemon body whose markers fit a scene body's within this is it


def match_bodies(true_markers, defined_markers):
    """Which defined body is which true one, by shape alone: for every pair with as many
    markers, the markers paired by their sorted distances to the others (the simulator's
    bodies have distinct distances), then a rigid fit; pairs fitting within MATCH_RMS_M
    are assigned one to one, best fits first (the Hungarian method on the fit RMS).
    Yields (true index, defined index, perm, R, t, rms): defined marker perm[m] is true
    marker m, defined = R @ true + t."""
    # deferred on purpose: loads SciPy's optimisers, SciPy's sparse graphs... only where used
    from scipy.optimize import linear_sum_assignment


    nt, nd = len(true_markers), len(defined_markers)
    cost = np.full((nt, nd), 1e9)
    fits = {}
    for i, a in enumerate(true_markers):
        for j, b in enumerate(defined_markers):
            b = np.asarray(b, dtype=np.float64)
            if len(a) != len(b):
                continue
            sig_a = np.sort(np.linalg.norm(a[:, None] - a[None], axis=2), axis=1)
            sig_b = np.sort(np.linalg.norm(b[:, None] - b[None], axis=2), axis=1)
            _, perm = linear_sum_assignment(
                np.linalg.norm(sig_a[:, None] - sig_b[None], axis=2))
            R, t, _ = rigid_fit(a, b[perm])
            rms = float(np.sqrt(np.mean(np.sum((a @ R.T + t - b[perm]) ** 2, axis=1))))
            if rms <= MATCH_RMS_M:
                cost[i, j] = rms
                fits[i, j] = (perm, R, t, rms)
    rows, cols = linear_sum_assignment(cost)
    for i, j in zip(rows, cols, strict=True):
        if (i, j) in fits:
            yield (int(i), int(j), *fits[i, j])
