"""Labelling unlabelled 3D points with a marker set: tracking, structure checks, ghosts.

The third seed labelled each frame from scratch by matching modules by their distances.
Here a whole take (`label_take`) starts from one global assignment on a window of frames
(daemon/markers/label_start.py), and the live per-frame API from that matching on one frame
(`initial_labels`); after that every marker is tracked: predicted from its velocity,
assigned to the nearest point by one global assignment, checked against its steadiest
neighbours' distances (which rejects ghosts and swaps), and a marker that was lost is
predicted from its neighbours' rigid motion since it was last seen (the shape carried
along), so it is re-identified when it reappears.

Live use (one frame at a time, e.g. in the daemon's pipeline):

    lab = Labeller(markerset, rate_hz=120)
    lab.seed(first_frame_xyz)          # optional: a labelled frame (n, 3), NaN = unseen
    labels, confidence = lab.update(points_xyz)   # (k,) marker index or -1, (k,) 0..1
    lab.positions                      # (n, 3) current labelled positions, NaN = not seen

Without a seed the first update labels the frame from the marker set alone.
"""

from __future__ import annotations

import warnings

import numpy as np
from scipy.optimize import linear_sum_assignment

from daemon.markers import label_kernels as kern
from daemon.markers.c3dio import Points, Take
from daemon.markers.label_modules import (
    module_template,
    order_modules,
    pair_distances,
    rigid_modules,
    rigid_residuals,
    template_sigma,
)
from daemon.markers.label_start import window_start
from daemon.markers.markerset import MarkerSet, signed_volume

K_NEIGHBOURS = 6
BIG = 1e6


class Labeller:
    """Frame-by-frame labeller; see the module docstring for the interface."""

    def __init__(self, markerset: MarkerSet, rate_hz: float = 120.0, gate_m: float = 0.04,
                 reacquire_gate_m: float = 0.12, noise_m: float = 0.003,
                 adapt: float = 0.02, smooth: float = 1.0, structure_limit: float = 2.0,
                 candidate_limit: float = 1.0, ambiguity: float = 4.0,
                 witnesses: bool = False, spread_gain: float = 2.0,
                 fresh_margin: float = 4.0, shape_check: bool = False,
                 suspect_frames: int = 30, module_reid: bool = True,
                 chi2_cost: bool = False, module_check: bool = True,
                 renew_sigma: float = 2.0, compiled: bool = True,
                 merge_m: float | None = None) -> None:
        self.ms = markerset
        n = markerset.n
        self.n = n
        self.rate_hz = rate_hz
        self.gate_m = gate_m
        self.reacquire_gate_m = reacquire_gate_m
        self.noise_m = noise_m
        # points closer than this are one marker seen twice (a file storing a trajectory
        # under two names, two reconstructions of one marker): never two markers of the set
        off = markerset.mean_m[~np.eye(n, dtype=bool)]
        closest = float(off[off > 0].min()) if (off > 0).any() else 1.0
        self.merge_m = min(2.0 * noise_m, 0.25 * closest) if merge_m is None else merge_m
        self.merged = 0          # points taken as another point's duplicate so far
        self.adapt = adapt
        self.smooth = smooth
        self.structure_limit = structure_limit
        self.candidate_limit = candidate_limit
        self.ambiguity = ambiguity
        self.witnesses = witnesses
        self.spread_gain = spread_gain
        self.suspect_frames = suspect_frames
        self.fresh_margin = fresh_margin
        self._support_spread = np.zeros(0)
        sd = markerset.sd_m.copy()
        np.fill_diagonal(sd, np.inf)
        self.nb = np.argsort(sd, axis=1)[:, :K_NEIGHBOURS]          # steadiest neighbours
        rows = np.arange(n)[:, None]
        self.nb_mean = markerset.mean_m[rows, self.nb].copy()
        self.nb_sd = markerset.sd_m[rows, self.nb]
        self.nb_subject = np.maximum(markerset.subject_sd_m, SUBJECT_REL * markerset.mean_m
                                     )[rows, self.nb]
        # prediction weights: how steadily each marker keeps its distance to each other
        w = 1.0 / (markerset.sd_m ** 2 + 0.005 ** 2)
        np.fill_diagonal(w, 0.0)
        self.pred_w = w / w.max(1, keepdims=True)
        # swap checks: pairs of markers close enough to be confused
        tol_all = 3.0 * np.sqrt(markerset.sd_m ** 2 + 2 * noise_m ** 2) + 0.004
        self.swap_w = np.where(markerset.sd_m < 0.02, 1.0 / tol_all ** 2, 0.0) * 9.0
        np.fill_diagonal(self.swap_w, 0.0)
        self.mean_all = markerset.mean_m.copy()
        iu = np.argwhere(np.triu(markerset.mean_m < 0.25, 1))
        self.swap_pairs = iu
        self.adapted = False
        self._tol_known = None
        self._tol_cache = None
        self._tol_frames = -1
        self.since_reacquired = np.zeros(n, int)
        self.known_frames = np.zeros(n, int)    # frames whose distances this take taught
        self.adapt_tol = _tolerance(markerset, noise_m)
        # segment shapes for the order check: the marker set's, replaced by this take's
        from itertools import permutations
        self.seg_checks = [(np.array(sg.markers), sg.shape_m.copy(),
                            np.array(list(permutations(range(len(sg.markers))))))
                           for sg in markerset.segments if 3 <= len(sg.markers) <= 5]
        self.shape_check = shape_check
        self.template_tol = _tolerance(markerset, noise_m)
        self.anchors = np.argsort(sd, axis=1)[:, :-1]     # all others, steadiest first
        # rigid modules (a segment and the markers that hold still with it, e.g. a foot's
        # tetrahedron with its ankle): re-identified jointly, by a proper rigid fit of the
        # module's own shape in this take (which tells a module from its mirror image)
        self.module_reid = module_reid
        self.chi2_cost = chi2_cost
        self.renew_sigma = renew_sigma
        self.compiled = compiled       # numba kernels (label_kernels); numpy twins otherwise
        self._sd2 = markerset.sd_m ** 2
        self.modules = rigid_modules(markerset)
        M = len(self.modules)
        width = max((len(m) for m in self.modules), default=1)
        self.mod_idx = np.zeros((M, width), int)
        self.mod_mask = np.zeros((M, width), bool)
        for k, m in enumerate(self.modules):
            self.mod_idx[k, :len(m)] = m
            self.mod_mask[k, :len(m)] = True
        self.mod_width = self.mod_mask.sum(1)
        self.mod_of = np.full(n, -1)
        for k, m in enumerate(self.modules):
            self.mod_of[m] = k
        self.mates = (self.mod_of[:, None] == self.mod_of[None]) & (self.mod_of[:, None] >= 0)
        np.fill_diagonal(self.mates, False)
        self.mod_shape = np.full((M, width, 3), np.nan)     # this take's shape, once seen
        self.mod_shape_first = self.mod_shape.copy()         # ... and the first one seen
        self.module_check = module_check
        self._mod_fit_now: np.ndarray | None = None
        self._maps_cache: dict = {}
        self.mod_sigma = np.array([np.sqrt(np.mean(markerset.sd_m[np.ix_(m, m)] ** 2))
                                   for m in self.modules]).reshape(M) + noise_m
        # the marker set's shape of each module, with its handedness, for modules not yet
        # seen whole in this take; looser by the spread between subjects
        self.mod_template = np.full((M, width, 3), np.nan)
        self.mod_template_sigma = np.zeros(M)
        for k, m in enumerate(self.modules):
            self.mod_template[k, :len(m)] = module_template(markerset, m)
            self.mod_template_sigma[k] = template_sigma(markerset, m, noise_m)
        self.pos = np.full((n, 3), np.nan)
        self.vel = np.zeros((n, 3))
        self.age = np.full(n, 10 ** 6)
        self.snap = np.full((n, n, 3), np.nan)
        self.frames = 0

    # ------------------------------------------------------------------ state
    @property
    def positions(self) -> np.ndarray:
        out = self.pos.copy()
        out[self.age > 0] = np.nan
        return out

    def _tol(self) -> np.ndarray:
        """Allowed deviation of a neighbour distance: spread of the body's motion, marker
        noise and, until the take's own distances are learned, the spread between
        subjects."""
        if self._tol_cache is not None and self._tol_frames == self.frames:
            return self._tol_cache          # known_frames only change in _commit/seed
        self._tol_frames = self.frames
        known = self.known_frames >= 30
        if self._tol_known is not None and np.array_equal(known, self._tol_known):
            return self._tol_cache
        both = known[:, None] & known[self.nb]
        subject = np.where(both, 0.0, self.nb_subject)
        self._tol_known = known
        self._tol_cache = 3.0 * np.sqrt(self.nb_sd ** 2 + subject ** 2
                                        + 2 * self.noise_m ** 2) + 0.004
        return self._tol_cache

    def seed(self, xyz: np.ndarray) -> None:
        """Start from a labelled frame (n, 3), NaN for markers not seen in it."""
        xyz = np.asarray(xyz, float)
        ok = np.isfinite(xyz).all(1)
        self.pos = np.where(ok[:, None], xyz, np.nan)
        self.vel[:] = 0.0
        self.age = np.where(ok, 0, 10 ** 6)
        self.snap[ok] = self.pos[None]
        self._learn_distances(self.pos, rate=1.0 if not self.adapted else self.adapt)
        self.known_frames[ok] = 10 ** 6
        self._tol_frames = -1
        self.adapted = True

    def seed_take(self, xyz: np.ndarray) -> None:
        """Start from several labelled frames (f, n, 3): distances from all of them."""
        d = np.linalg.norm(xyz[:, :, None] - xyz[:, None], axis=3)  # (f, n, n)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            med = np.nanmedian(d, axis=0)
        self.mean_all = np.where(np.isfinite(med), med, self.mean_all)
        seen = np.isfinite(xyz).all(2).any(0)
        self.known_frames[seen] = 10 ** 6
        self._tol_frames = -1
        # pairs seen in the seed frames: this body's distances, known; pairs not seen
        # (a marker hidden throughout): the set's, as loose as another subject's
        self.adapt_tol = np.where(np.isfinite(med), 3.0 * np.sqrt(
            self.ms.sd_m ** 2 + 2 * self.noise_m ** 2) + 0.004, _tolerance(self.ms, self.noise_m))
        self.nb_mean = self.mean_all[np.arange(self.n)[:, None], self.nb]
        self.adapted = True
        for k, (idx, _, perms) in enumerate(self.seg_checks):
            full = np.isfinite(xyz[:, idx]).all(axis=(1, 2))
            if full.any():
                shape = xyz[np.nonzero(full)[0][-1]][idx]
                self.seg_checks[k] = (idx, shape - shape.mean(0), perms)
        if len(xyz) >= 2:
            self.seed(xyz[-2])
            self.update_labelled(xyz[-1])
        else:
            self.seed(xyz[-1])

    def start(self, points: np.ndarray, labels: np.ndarray) -> None:
        """Start from one frame's points and their labels (-1 = none)."""
        P = np.asarray(points, float).reshape(-1, 3)
        cur = np.full((self.n, 3), np.nan)
        got = labels >= 0
        cur[labels[got]] = P[got]
        self._commit(cur, np.isfinite(cur).all(1))

    def update_labelled(self, xyz: np.ndarray) -> None:
        """Advance the tracker with a frame whose labels are known (seed frames)."""
        ok = np.isfinite(xyz).all(1)
        self._commit(np.where(ok[:, None], xyz, np.nan), ok)

    def _learn_distances(self, cur: np.ndarray, rate: float) -> None:
        """Follow this take's own marker distances (another subject, other placement)."""
        seen = np.isfinite(cur).all(1)
        idx = np.nonzero(seen)[0]
        x = cur[idx]
        d = np.linalg.norm(x[:, None] - x[None], axis=2)
        sub = self.mean_all[np.ix_(idx, idx)]
        step = d - sub
        # robust: a distance far off (a swap, a ghost) teaches nothing
        step[np.abs(step) > self.adapt_tol[np.ix_(idx, idx)]] = 0.0
        self.mean_all[np.ix_(idx, idx)] = sub + rate * step
        self.known_frames[idx] += 1
        self._tol_frames = -1
        self.nb_mean = self.mean_all[np.arange(self.n)[:, None], self.nb]

    # ------------------------------------------------------------------ one frame
    def update(self, points: np.ndarray, steps: int = 1) -> tuple[np.ndarray, np.ndarray]:
        """Label one frame's points (k, 3): marker index per point (-1 = ghost/unknown)
        and a confidence 0..1 per point. `steps`: frames since the previous update (a
        live stage that skipped frames), so that motion is predicted over the real gap.
        Points closer than `merge_m` are labelled as one: each takes the label of the
        first of them."""
        P = np.asarray(points, float).reshape(-1, 3)
        rep = _duplicates(P, self.merge_m)
        if rep is None:
            return self._update(P, steps)
        keep = np.nonzero(rep == np.arange(len(P)))[0]
        self.merged += len(P) - len(keep)
        lab, conf = self._update(P[keep], steps)
        row = np.full(len(P), -1)
        row[keep] = np.arange(len(keep))
        return lab[row[rep]], conf[row[rep]]

    def _update(self, P: np.ndarray, steps: int) -> tuple[np.ndarray, np.ndarray]:
        steps = max(1, int(steps))
        self._P = P
        k = len(P)
        n = self.n
        if not np.isfinite(self.pos).any():
            lab = initial_labels(P, self.ms)
            cur = np.full((n, 3), np.nan)
            got = lab >= 0
            cur[lab[got]] = P[got]
            ok = np.isfinite(cur).all(1)
            self._commit(cur, ok, steps)
            return lab, np.where(got, 0.5, 0.0)

        marker_of = np.full(k, -1)
        point_of = np.full(n, -1)
        self._new_now = np.zeros(n, bool)      # markers found again in this frame
        # 1. tracked markers: constant-velocity prediction, one global assignment
        tracked = np.nonzero(self.age <= 2)[0]
        if len(tracked) and k:
            q = self.pos[tracked] + self.vel[tracked] * (self.age[tracked, None] + steps)
            diff = q[:, None] - P[None]
            cost = np.sqrt(np.einsum("tki,tki->tk", diff, diff))
            # the prediction's error grows with the time since the last update
            cost[~(cost <= self.gate_m * steps)] = BIG     # also NaN: no prediction
            r, c = linear_sum_assignment(cost)
            good = cost[r, c] < BIG
            point_of[tracked[r[good]]] = c[good]
            marker_of[c[good]] = tracked[r[good]]
        cur = np.full((n, 3), np.nan)
        has = point_of >= 0
        cur[has] = P[point_of[has]]

        # 2. structure check: a marker far off its steady neighbours' distances is a
        #    ghost or a swap; drop it and let step 3 find it again.
        err = self._structure_error(cur)
        bad = has & (err > self.structure_limit)
        if bad.any():
            marker_of[point_of[bad]] = -1
            point_of[bad] = -1
            cur[bad] = np.nan

        # 3. lost and rejected markers: predicted from their neighbours' motion since they
        #    were last seen; assigned among the points left over.
        lost = np.nonzero(point_of < 0)[0]
        free = np.nonzero(marker_of < 0)[0]
        if len(lost) and len(free):
            pred = self._predict_from_neighbours(lost, cur)
            spread = self._support_spread
            dist = np.linalg.norm(pred[:, None] - P[free][None], axis=2)
            dist[~np.isfinite(dist)] = BIG
            age = np.minimum(self.age[lost], 120)
            gate = self.reacquire_gate_m + 0.002 * age
            sigma = 0.012 + 0.0005 * age + self.spread_gain * spread
            # distances to labelled neighbours must also fit
            cerr, cnum = self._candidate_error(lost, P[free], cur)
            if self.chi2_cost:
                cost = (dist / sigma[:, None]) ** 2 + self._cand_chi2
            else:
                cost = (dist / sigma[:, None]) ** 2 + 4.0 * cerr ** 2
            cost[(dist > gate[:, None]) | (cerr > self.candidate_limit)] = BIG
            # never seen since the start: found by distances alone, from >= 3 neighbours
            never = ~np.isfinite(self.snap[lost, lost]).all(1)
            fresh = never.copy()
            # long lost and nothing near its prediction: the prediction may be stale (a
            # ghost once taken for it); find it by its distances to everyone instead
            fresh |= (self.age[lost] > 20) & (cost >= BIG).all(1)
            if fresh.any():
                cost[fresh] = self._fresh_cost(lost[fresh], P[free], cur)
            if self.module_reid:
                self._module_refind(lost, P[free], cur, cost, cerr)
                self._module_assign(lost, P[free], cur, cost, never, point_of, marker_of)
            r, c = linear_sum_assignment(cost)
            good = cost[r, c] < BIG
            # ambiguous: another lost marker fits the same point almost as well
            if len(lost) > 1:
                alt = cost[:, c].copy()
                alt[r, np.arange(len(c))] = np.inf
                second = alt.min(0)
                good &= ~(second < cost[r, c] + self.ambiguity)
            point_of[lost[r[good]]] = free[c[good]]
            marker_of[free[c[good]]] = lost[r[good]]
            cur[lost[r[good]]] = P[free[c[good]]]
            self._new_now[lost[r[good]]] = True

        changed = len(lost) > 0 or bad.any()
        if changed:
            err = self._structure_error(cur)
        if self._repair_swaps(cur, point_of, marker_of, err):
            err = self._structure_error(cur)
        has = point_of >= 0
        conf_m = np.where(has, np.exp(-2.0 * np.where(np.isnan(err), 0.5, err) ** 2), 0.0)
        self._commit(cur, has, steps)
        conf = np.zeros(k)
        conf[point_of[has]] = conf_m[has]
        return marker_of, conf

    def _structure_error(self, cur: np.ndarray) -> np.ndarray:
        """Per marker: mean over its labelled neighbours of |d - mean| / tolerance (each
        capped at 3, so one bad neighbour cannot condemn a marker alone)."""
        if self.compiled:
            return kern.structure_error(cur, self.nb, self.nb_mean, self._tol())
        diff = cur[:, None] - cur[self.nb]
        d = np.sqrt(np.einsum("nki,nki->nk", diff, diff))
        e = np.abs(d - self.nb_mean) / self._tol()
        ok = np.isfinite(e)
        num = ok.sum(1)
        mean = np.where(ok, np.minimum(e, 3.0), 0.0).sum(1) / np.maximum(num, 1)
        return np.where(num > 0, mean, np.nan)

    def _fresh_cost(self, markers: np.ndarray, P: np.ndarray, cur: np.ndarray) -> np.ndarray:
        """Cost of each point for markers never seen yet: their distances to every labelled
        marker against the marker set, weighted by steadiness (as when a take starts from
        the template); only a clear winner (4 units better than the runner-up) counts."""
        if self.compiled:
            return kern.fresh_cost(markers, P, cur, self.anchors, self.adapt_tol,
                                   self.mean_all, self.fresh_margin, BIG)
        seen = np.isfinite(cur).all(1)
        if seen.sum() < 3:
            return np.full((len(markers), len(P)), BIG)
        anchors = self.anchors[markers]                                  # (M, A)
        ok = seen[anchors]
        tol = self.adapt_tol[markers[:, None], anchors]
        w = np.where(ok, 1.0 / tol ** 2, 0.0)
        mu = self.mean_all[markers[:, None], anchors]
        x = np.where(ok[:, :, None], cur[anchors], 0.0)                  # (M, A, 3)
        diff = P[None, :, None] - x[:, None]                             # (M, k, A, 3)
        d = np.sqrt(np.einsum("mkai,mkai->mka", diff, diff))
        e2 = np.minimum((d - mu[:, None]) ** 2 * w[:, None] * 9.0, 16.0)
        cost = (e2 * w[:, None]).sum(2) / np.maximum(w.sum(1), 1e-12)[:, None]
        cost[ok.sum(1) < 3] = BIG
        cost = np.where(cost < 1.0, cost, BIG)
        if cost.shape[1] >= 2:
            part = np.partition(cost, 1, axis=1)
            unclear = part[:, 1] < part[:, 0] + self.fresh_margin
            cost[unclear] = BIG
        return cost

    def _candidate_error(self, markers: np.ndarray, P: np.ndarray, cur: np.ndarray
                         ) -> np.ndarray:
        """(len(markers), len(P)): neighbour-distance error if marker took that point."""
        if self.compiled:
            mean, num, self._cand_chi2 = kern.candidate_error(
                markers, P, cur, self.nb, self.nb_mean, self._tol())
            return mean, num
        nbx = cur[self.nb[markers]]                                    # (L, K, 3)
        d = np.linalg.norm(P[None, :, None] - nbx[:, None], axis=3)    # (L, k, K)
        e = np.abs(d - self.nb_mean[markers][:, None]) / self._tol()[markers][:, None]
        ok = np.isfinite(e)
        num = ok.sum(2)
        mean = np.where(ok, np.minimum(e, 3.0), 0.0).sum(2) / np.maximum(num, 1)
        # the same as a sum of squares in units of the distances' SD (tolerance / 3), each
        # capped at 4 SD: a sum tells two candidates apart where a mean dilutes
        self._cand_chi2 = np.where(ok, np.minimum(9.0 * e * e, 16.0), 0.0).sum(2)
        return mean, num

    def _predict_from_neighbours(self, lost: np.ndarray, cur: np.ndarray) -> np.ndarray:
        """Where each lost marker should be now: the rigid motion, from when it was last
        seen to now, of the markers seen both then and now, weighted by how steadily they
        keep their distance to it (weighted Kabsch, batched over lost markers); with too
        little support, their weighted mean translation; with none, its last position
        moved by its last velocity."""
        if self.compiled:
            A = self.snap[lost]
            W = self.pred_w[lost]
            fallback = self.pos[lost] + self.vel[lost] * \
                np.minimum(self.age[lost] + 1, 3)[:, None]
            pred, self._support_spread = kern.predict_from_neighbours(
                A, cur, W, W.max(1), self._sd2[lost], A[np.arange(len(lost)), lost], fallback)
            return pred
        A = self.snap[lost]                                     # (L, n, 3) then
        B = cur                                                 # (n, 3) now
        w = self.pred_w[lost] * (np.isfinite(A).all(2) & np.isfinite(B).all(1)[None])
        A0 = np.where(np.isnan(A), 0.0, A)
        B0 = np.where(np.isnan(B), 0.0, B)
        sw = w.sum(1)
        ca = np.einsum("ln,lni->li", w, A0) / np.maximum(sw, 1e-12)[:, None]
        cb = (w @ B0) / np.maximum(sw, 1e-12)[:, None]
        H = np.einsum("ln,lni,lnj->lij", w, A0 - ca[:, None], B0[None] - cb[:, None])
        U, S, Vt = np.linalg.svd(H)
        d = np.sign(np.linalg.det(np.einsum("lji,lkj->lik", Vt, U)))
        D = np.ones((len(lost), 3))
        D[:, 2] = d
        R = np.einsum("lji,lj,lkj->lik", Vt, D, U)               # V D U^T
        support = (w > 0.05 * self.pred_w[lost].max(1, keepdims=True)).sum(1)
        # how loosely the markers used keep their distance to the lost one (weighted SD)
        sd2 = self.ms.sd_m[lost] ** 2
        self._support_spread = np.sqrt((w * sd2).sum(1) / np.maximum(sw, 1e-12))
        R[(support < 3) | (S[:, 1] <= 1e-12 * np.maximum(S[:, 0], 1e-30))] = np.eye(3)
        last = A[np.arange(len(lost)), lost]                     # (L, 3)
        pred = np.einsum("lij,lj->li", R, last - ca) + cb
        none = sw <= 0
        if none.any():
            pred[none] = self.pos[lost[none]] + self.vel[lost[none]] * \
                np.minimum(self.age[lost[none]] + 1, 3)[:, None]
        return pred

    def _check_segment_order(self, cur, point_of, marker_of, suspect) -> bool:
        """Within a segment of 3-5 markers where one was just found again: the order of
        its points that fits the segment's shape best by a proper rigid motion. Labels
        rotated around a foot keep most distances but not the shape and its handedness."""
        if not self.shape_check:
            return False
        done = False
        for idx, shape, perms in self.seg_checks:
            if not suspect[idx].any() or (point_of[idx] < 0).any():
                continue
            B = cur[idx][perms]                                        # (p, k, 3)
            cb = B.mean(1)
            H = np.einsum("ki,pkj->pij", shape, B - cb[:, None])
            U, _, Vt = np.linalg.svd(H)
            d = np.sign(np.linalg.det(np.einsum("pji,pkj->pik", Vt, U)))
            D = np.ones((len(perms), 3))
            D[:, 2] = d
            R = np.einsum("pji,pj,pkj->pik", Vt, D, U)
            fit = np.einsum("pij,kj->pki", R, shape) + cb[:, None]
            res = ((fit - B) ** 2).sum((1, 2))
            best = int(np.argmin(res))
            if best == 0 or res[best] > 0.25 * res[0] or res[0] < len(idx) * 0.005 ** 2:
                continue
            new_pts = point_of[idx][perms[best]]
            point_of[idx] = new_pts
            marker_of[new_pts] = idx
            old_pos, old_vel = self.pos[idx].copy(), self.vel[idx].copy()
            cur[idx] = cur[idx][perms[best]]
            self.pos[idx] = old_pos[perms[best]]
            self.vel[idx] = old_vel[perms[best]]
            done = True
        return done

    def _witness_swaps(self, cur, point_of, marker_of, err, suspect) -> bool:
        """Swap close markers i and j when a learned tetrahedron (i, j, a, b) has turned
        inside out while its witnesses a and b fit their neighbours well."""
        q = self.ms.pair_quads
        if not len(q) or not self.witnesses:
            return False
        i, j, a, b = q.T
        e = np.nan_to_num(err, nan=9.0)
        use = (suspect[i] | suspect[j]) & (point_of[i] >= 0) & (point_of[j] >= 0) & \
            (point_of[a] >= 0) & (point_of[b] >= 0) & (e[a] < 0.5) & (e[b] < 0.5)
        if not use.any():
            return False
        v = signed_volume(cur, q[use])
        wrong = (np.sign(v) != self.ms.pair_sign[use]) & \
            (np.abs(v) > 0.3 * self.ms.pair_volume[use])
        done = False
        touched: set[int] = set()
        for x, y in q[use][wrong][:, :2]:
            x, y = int(x), int(y)
            if x in touched or y in touched:
                continue
            touched.update((x, y))
            px, py = point_of[x], point_of[y]
            point_of[x], point_of[y] = py, px
            marker_of[px], marker_of[py] = y, x
            cur[[x, y]] = cur[[y, x]]
            self.pos[[x, y]] = self.pos[[y, x]]
            self.vel[[x, y]] = self.vel[[y, x]]
            done = True
        return done

    def _check_modules(self, cur, point_of, marker_of, suspect) -> bool:
        """Rigid modules against their shape in this take: one whose labelled points do
        not fit it (labels rotated within a foot, a wrist pair swapped, a ghost taken) is
        relabelled by the assignment of its points to its markers that fits best by a
        proper rigid motion. Also decides which modules fit well enough to renew their
        shape (`_commit`)."""
        self._mod_fit_now = np.zeros(len(self.modules), bool)
        if not self.module_check or not len(self.modules) or \
                not (self._new_now.any() or self.frames % 8 == 0):
            return False
        has = point_of >= 0
        w = (has[self.mod_idx] & self.mod_mask).astype(float)           # (M, W)
        known = (np.isfinite(self.mod_shape).all(2) | ~self.mod_mask).all(1)
        sus = (suspect[self.mod_idx] & self.mod_mask).any(1)
        # a module is looked at when one of its markers was found again in this frame,
        # and every 8th frame (to renew its shape, and to catch what slipped through)
        new = (self._new_now[self.mod_idx] & self.mod_mask).any(1)
        look = known & (w.sum(1) >= 3) & (new | (self.frames % 8 == 0))
        if not look.any():
            return False
        ks = np.nonzero(look)[0]
        shapes = self.mod_shape[ks]
        X = cur[self.mod_idx[ks]]
        r2 = self._residuals(np.where(np.isnan(shapes), 0.0, shapes),
                             np.where(np.isnan(X), 0.0, X), w[ks])
        worst = r2.max(1) / self.mod_sigma[ks] ** 2
        # the shape is renewed only from a labelling that fits it closely: renewing it
        # from a looser fit lets a wrong labelling (a ghost, a rotation) become the shape
        fit = worst <= self.renew_sigma ** 2
        # ... or its first shape in this take: a shape that followed the markers while they
        # slid (a head band slipping) returns when they return
        miss = np.nonzero(~fit)[0]
        if len(miss):
            first = self.mod_shape_first[ks[miss]]
            r2f = self._residuals(np.where(np.isnan(first), 0.0, first),
                                  np.where(np.isnan(X[miss]), 0.0, X[miss]), w[ks[miss]])
            fit[miss] = r2f.max(1) / self.mod_sigma[ks[miss]] ** 2 <= self.renew_sigma ** 2
        self._mod_fit_now[ks] = fit
        done = False
        small = self.mod_mask[ks].sum(1) <= 5     # a back of 6+ markers bends too much
        for k in ks[(worst > 3.0 ** 2) & sus[ks] & small]:
            done |= self._reorder_module(int(k), cur, point_of, marker_of)
        return done

    def _reorder_module(self, k: int, cur, point_of, marker_of) -> bool:
        idx = self.modules[k]
        m = len(idx)
        held = np.nonzero(point_of[idx] >= 0)[0]                          # members with a point
        pts = point_of[idx[held]]
        maps = self._maps(m, len(held))                                   # (H, p): member per point
        if len(maps) > 5040:
            return False
        H = len(maps)
        X = np.zeros((H, m, 3))
        w = np.zeros((H, m))
        rows = np.arange(H)[:, None]
        X[rows, maps] = cur[idx[held]][None]
        w[rows, maps] = 1.0
        shape = self.mod_shape[k, :m]
        r2 = self._residuals(shape, X, w)
        tot = r2.sum(1)
        same = (maps == held[None]).all(1)
        ident = float(tot[same][0]) if same.any() else np.inf
        b = int(np.argmin(tot))
        sigma = self.mod_sigma[k]
        if same[b] or r2[b].max() > (2.5 * sigma) ** 2 or tot[b] > 0.25 * ident:
            return False
        # a runner-up nearly as good (a flat module's mirror twin, a triangle of a
        # four-marker module) means the fit cannot tell which relabelling is right
        if len(tot) > 2 and np.partition(tot, 1)[1] < tot[b] + 9.0 * sigma ** 2:
            return False
        new_member = maps[b]                                              # for each point
        old_pos, old_vel = self.pos[idx].copy(), self.vel[idx].copy()
        point_of[idx] = -1
        cur[idx] = np.nan
        for q, j_old, j_new in zip(pts, held, new_member, strict=True):
            point_of[idx[j_new]] = q
            marker_of[q] = idx[j_new]
            cur[idx[j_new]] = self._P[q]
            self.pos[idx[j_new]] = old_pos[j_old]
            self.vel[idx[j_new]] = old_vel[j_old]
        return True

    def _residuals(self, shape: np.ndarray, X: np.ndarray, w: np.ndarray) -> np.ndarray:
        """Squared residuals of proper rigid fits (see `rigid_residuals`)."""
        if self.compiled:
            return kern.rigid_residuals(np.ascontiguousarray(np.broadcast_to(shape, X.shape)),
                                        np.ascontiguousarray(X), np.ascontiguousarray(w),
                                        True)
        return rigid_residuals(shape, X, w, True)

    def _maps(self, m: int, p: int) -> np.ndarray:
        key = (m, p)
        if key not in self._maps_cache:
            from itertools import permutations
            self._maps_cache[key] = np.array(list(permutations(range(m), p)), int
                                             ).reshape(-1, p)
        return self._maps_cache[key]

    def _repair_swaps(self, cur: np.ndarray, point_of: np.ndarray, marker_of: np.ndarray,
                      err: np.ndarray) -> bool:
        """Swap two labelled markers when their distances to the other markers fit much
        better the other way round (a swap that tracking alone would carry on)."""
        i, j = self.swap_pairs[:, 0], self.swap_pairs[:, 1]
        suspect = (self.since_reacquired < self.suspect_frames) | (err > 0.5)   # NaN: False
        done = self._witness_swaps(cur, point_of, marker_of, err, suspect)
        done |= self._check_segment_order(cur, point_of, marker_of, suspect)
        done |= self._check_modules(cur, point_of, marker_of, suspect)
        if not suspect.any():
            return done
        ok = np.isfinite(cur[i]).all(1) & np.isfinite(cur[j]).all(1) & (suspect[i] | suspect[j])
        if not ok.any():
            return done
        i, j = i[ok], j[ok]
        scores = kern.swap_scores if self.compiled else _swap_scores
        # a marker found again in this very frame (perhaps a ghost) is no witness
        keep, swap = scores(cur, i, j, self.swap_w, self.mean_all, ~self._new_now)
        better = (swap < 0.25 * keep) & (keep - swap > 25.0)
        for a, b in zip(i[better], j[better], strict=True):
            if point_of[a] < 0 or point_of[b] < 0:
                continue
            pa, pb = point_of[a], point_of[b]
            point_of[a], point_of[b] = pb, pa
            marker_of[pa], marker_of[pb] = b, a
            cur[[a, b]] = cur[[b, a]]
            self.pos[[a, b]] = self.pos[[b, a]]
            self.vel[[a, b]] = self.vel[[b, a]]
            done = True
        return done

    def _module_refind(self, lost: np.ndarray, Pf: np.ndarray, cur: np.ndarray,
                       cost: np.ndarray, cerr: np.ndarray) -> None:
        """A rigid module hidden whole (a forearm, a foot), or all but one marker of it,
        is found again as a whole: 4 or more points (left-over ones, and the one marker
        seen) that fit its shape in this take. Marker by marker it cannot be: its
        markers' predictions are far off (a swinging arm) and their distances to the rest
        of the body too loose to tell its points apart. Hypotheses grow member by member
        through the pair distances; a best fit with no rival near it, and whose points no
        other module claims, is forced into `cost`."""
        if not len(self.modules) or len(Pf) < 3:
            return
        seen = np.isfinite(cur).all(1)
        # modules of 4+ markers with at most one marker seen (most frames: none)
        hidden = (self.mod_width >= 4) & ((seen[self.mod_idx] & self.mod_mask).sum(1) <= 1)
        if not hidden.any():
            return
        row_of = np.full(self.n, -1)
        row_of[lost] = np.arange(len(lost))
        F = len(Pf)
        claims = []
        for k in np.nonzero(hidden)[0]:
            idx = self.modules[k]
            m = len(idx)
            shown = seen[idx]
            if (row_of[idx[~shown]] < 0).any():
                continue
            shape = self.mod_shape[k, :m]
            if not np.isfinite(shape).all():
                continue
            rows = row_of[idx]
            if (cerr[rows[~shown]] <= 1.5).any(0).sum() + shown.sum() < 4:
                continue                 # not 4 points it could take
            # the marker seen, if any, is a point every hypothesis keeps
            Pa = np.vstack([Pf, cur[idx[shown]]])
            D = pair_distances(Pa)
            sigma = self.mod_sigma[k]
            S = pair_distances(shape)
            tol = 3.0 * np.sqrt(2.0) * sigma + 0.005
            hyps = np.full((1, 0), -1, int)
            for j in range(m):
                if shown[j]:
                    q, keep_none = np.array([F]), False
                else:
                    # points it may take: its distances to the labelled body fit loosely
                    q, keep_none = np.nonzero(cerr[rows[j]] <= 1.5)[0], True
                a = hyps >= 0                                                # (h, j)
                d = D[q[:, None, None], np.maximum(hyps, 0)[None]]             # (c, h, j)
                ok = (~a[None] | (np.abs(d - S[j, :j]) <= tol)).all(2)
                ok &= ~(hyps[None] == q[:, None, None]).any(2)
                c, h = np.nonzero(ok)
                grown = [np.hstack([hyps[h], q[c][:, None]])]
                if keep_none:
                    grown.append(np.hstack([hyps, np.full((len(hyps), 1), -1)]))
                hyps = np.vstack(grown)
                hyps = hyps[(hyps < 0).sum(1) <= m - 4]
                if not len(hyps) or len(hyps) > 20000:
                    break
            if not len(hyps) or hyps.shape[1] < m:
                continue
            got = hyps >= 0
            X = np.where(got[:, :, None], Pa[np.maximum(hyps, 0)], 0.0)
            r2 = self._residuals(shape, X, got.astype(float))
            score = r2.sum(1) / sigma ** 2 + 9.0 * (~got).sum(1)
            score[(r2 > (2.5 * sigma) ** 2).any(1)] = np.inf
            b = int(np.argmin(score))
            if not np.isfinite(score[b]):
                continue
            best = hyps[b]
            # a rival as good that labels a point otherwise (a flat module's mirror twin);
            # one that only adds or leaves out a marker agrees with the best
            differ = got & (hyps != best[None]) & ((best[None] >= 0) |
                                                   np.isin(hyps, best[best >= 0]))
            rival = differ.any(1) & (score < score[b] + 9.0)
            if not rival.any():
                claims.append((rows[~shown], best[~shown]))
        used = [set(best[best >= 0].tolist()) for _, best in claims]
        for c, (rows, best) in enumerate(claims):
            if any(used[c] & u for d, u in enumerate(used) if d != c):
                continue          # two modules (left and right forearm) claim a point
            for j in range(len(rows)):
                cost[rows[j]] = BIG
                if best[j] >= 0:
                    cost[:, best[j]] = BIG
                    cost[rows[j], best[j]] = 0.0

    def _suspects_relabelled(self, idx, lm, rows, cand, shape, sigma, kept_score, Pf, cur,
                             cost, point_of, marker_of) -> bool:
        """The module's markers found again lately (suspects) decided again with its
        lost ones: a wrist's two markers, found one at a time beside the finger marker
        alone, are easily taken for each other, and only the module's next marker to show
        tells. Every assignment of suspects and lost markers to the suspects' points and
        the lost markers' candidates is fitted; one that moves a suspect is applied when it
        fits 4+ points and beats keeping the suspects (`kept_score`) by 9 units, with no
        rival as good that places them otherwise."""
        seen = np.isfinite(cur).all(1)
        sus = idx[seen[idx] & (self.since_reacquired[idx] < self.suspect_frames)]
        if not len(sus) or len(sus) + len(lm) > 5:
            return False
        F = len(Pf)
        pts = point_of[sus]
        Pa = np.vstack([Pf, self._P[pts]])
        options = [np.r_[-1, F + np.arange(len(sus))] for _ in sus] + \
            [np.r_[-1, np.nonzero(c)[0], F + np.arange(len(sus))] for c in cand]
        members = np.r_[sus, lm]
        hyps = _injective_product(options)
        if len(hyps) > 4096:
            return False
        moved = (hyps[:, :len(sus)] != F + np.arange(len(sus))[None]).any(1)
        if not moved.any():
            return False
        hyps, H = hyps[moved], int(moved.sum())
        local = np.searchsorted(idx, members) if np.all(np.diff(idx) > 0) else \
            np.array([list(idx).index(m) for m in members])
        fixed = seen[idx] & ~np.isin(idx, sus)
        x0 = np.where(fixed[:, None], cur[idx], 0.0)
        X = np.broadcast_to(x0, (H, len(idx), 3)).copy()
        w = np.broadcast_to(fixed, (H, len(idx))).astype(float)
        got = hyps >= 0
        for j in range(len(members)):
            X[got[:, j], local[j]] = Pa[hyps[got[:, j], j]]
            w[:, local[j]] = got[:, j]
        r2 = self._residuals(shape, X, w)
        score = r2.sum(1) / sigma ** 2 + 9.0 * (~got).sum(1)
        score[(r2 > (3.5 * sigma) ** 2).any(1) | (w.sum(1) < 4)] = np.inf
        b = int(np.argmin(score))
        if not score[b] < kept_score - 9.0:
            return False
        best = hyps[b]
        differ = got & (hyps != best[None]) & ((best[None] >= 0) |
                                                np.isin(hyps, best[best >= 0]))
        if (differ.any(1) & (score < score[b] + 9.0)).any():
            return False
        # apply: the suspects' points go where the fit puts them; the lost markers'
        # free points are forced into `cost`
        old_pos, old_vel = self.pos[sus].copy(), self.vel[sus].copy()
        point_of[sus] = -1
        marker_of[pts] = -1
        cur[sus] = np.nan
        for j, mkr in enumerate(members):
            q = best[j]
            if q >= F:                                    # a suspect's point
                s_old = q - F
                point_of[mkr] = pts[s_old]
                marker_of[pts[s_old]] = mkr
                cur[mkr] = self._P[pts[s_old]]
                self.pos[mkr] = old_pos[s_old]
                self.vel[mkr] = old_vel[s_old]
        for j in range(len(lm)):
            cost[rows[j]] = BIG
            q = best[len(sus) + j]
            if 0 <= q < F:
                cost[:, q] = BIG
                cost[rows[j], q] = 0.0
        return True

    def _module_assign(self, lost: np.ndarray, Pf: np.ndarray, cur: np.ndarray,
                       cost: np.ndarray, never: np.ndarray, point_of=None,
                       marker_of=None) -> None:
        """Re-identify the lost markers of each rigid module jointly: every assignment of
        its lost markers to candidate points (or to none) is scored by a proper rigid fit
        of the module's shape in this take to its labelled and assigned points. Marker by
        marker, two markers at equal distances from the visible ones (a foot's LMT5 and
        LTOE from its heel and ankle) or a ghost that fits one marker's distances can take
        the wrong point; the module's shape and handedness tell. A clear winner is forced
        into `cost`; a tie blocks the markers it concerns for this frame (they wait for
        more of the module to show)."""
        mk = self.mod_of[lost]
        inmod = mk >= 0
        if not inmod.any():
            return
        seen = np.isfinite(cur).all(1)
        # candidates: the marker's own gate, or (with 2+ module mates seen) distances to
        # its mates that fit, for all lost module markers at once
        lm_all = lost[inmod]
        # within the marker's own gate, or no gate (never seen in this take)
        own_all = (cost[inmod] < BIG) | never[inmod][:, None]
        cand_all = own_all.copy()
        if self.compiled:
            cand_all = kern.module_candidates(lm_all, self.mates, cur, Pf, self.mean_all,
                                              self.adapt_tol, cand_all)
        else:
            cand_all = _module_candidates(lm_all, self.mates, cur, Pf, self.mean_all,
                                          self.adapt_tol, cand_all)
        has_cand = cand_all.any(1)
        if not has_cand.any():
            return
        row_of = np.full(self.n, -1)
        row_of[lost] = np.arange(len(lost))
        sub_of = np.full(self.n, -1)
        sub_of[lm_all] = np.arange(len(lm_all))
        for k in np.unique(mk[inmod][has_cand]):
            idx = self.modules[k]
            lm = idx[row_of[idx] >= 0]
            anchors = idx[seen[idx]]
            rows = row_of[lm]
            cand = cand_all[sub_of[lm]]                                      # (l, F)
            own = own_all[sub_of[lm]]
            n_cand = cand.sum(1)
            if not n_cand.any() or len(anchors) + (n_cand > 0).sum() < 3 \
                    or np.prod(n_cand + 1) > 4096:
                continue
            shape = self.mod_shape[k, :len(idx)]
            sigma = self.mod_sigma[k]
            template = not np.isfinite(shape).all()
            if template:
                # not seen whole in this take yet: the marker set's shape, looser
                shape = self.mod_template[k, :len(idx)]
                sigma = self.mod_template_sigma[k]
            hyps = _injective_product([np.r_[-1, np.nonzero(c)[0]] for c in cand])
            H = len(hyps)
            x0 = cur[idx]
            X = np.broadcast_to(np.where(np.isnan(x0), 0.0, x0), (H, len(idx), 3)).copy()
            w = np.broadcast_to(seen[idx], (H, len(idx))).astype(float)
            pos = np.searchsorted(idx, lm) if np.all(np.diff(idx) > 0) else \
                np.array([list(idx).index(m) for m in lm])
            got = hyps >= 0
            for j in range(len(lm)):
                X[got[:, j], pos[j]] = Pf[hyps[got[:, j], j]]
                w[:, pos[j]] = got[:, j]
            r2 = self._residuals(shape, X, w)
            first = self.mod_shape_first[k, :len(idx)]
            if np.isfinite(first).all() and \
                    np.abs(pair_distances(first) - pair_distances(shape)).max() > 2 * sigma:
                # the shape followed markers that slid; the first one may fit again
                r2f = self._residuals(first, X, w)
                r2 = np.where((r2f.sum(1) < r2.sum(1))[:, None], r2f, r2)
            total = w.sum(1)
            # a point outside a marker's own gate, found by its distances to its mates,
            # needs a fit that tests more than those distances (3 points have no more)
            foreign = (got & ~own[np.arange(len(lm))[None], np.maximum(hyps, 0)]).any(1)
            bad = ((r2 > (3.5 * sigma) ** 2).any(1)) | ((total < 3) & got.any(1)) | \
                (foreign & (total < 4))
            score = r2.sum(1) / sigma ** 2 + 9.0 * (~got).sum(1)
            score[bad] = np.inf
            b = int(np.argmin(score))
            # markers found lately are decided again only when keeping them leaves a lost
            # marker with candidates unplaced (the fit then may say they are mixed up)
            if not template and point_of is not None and \
                    (not np.isfinite(score[b]) or ((hyps[b] < 0) & (n_cand > 0)).any()) and \
                    self._suspects_relabelled(idx, lm, rows, cand, shape, sigma, score[b],
                                              Pf, cur, cost, point_of, marker_of):
                continue
            if not np.isfinite(score[b]):
                continue
            best = hyps[b]
            used = best[best >= 0]
            conflict = (got & (hyps != best[None]) &
                        ((best[None] >= 0) | np.isin(hyps, used))).any(1)
            # a rival that places fewer markers is no tie: it leaves a point unexplained
            near = conflict & (score < score[b] + 6.0) & (got.sum(1) >= got[b].sum())
            agree = ~(near[:, None] & (hyps != best[None])).any(0)
            # a marker is decided here only where a fit could judge it (3+ points)
            judged = (got & (total >= 3)[:, None]).any(0) | (best >= 0)
            # a fit of this take's shape to 4+ points decides; the marker set's shape, or
            # 3 points, only offer the fit's cost against other lost markers' own costs
            strong = not template and total[b] >= 4
            fit_cost = r2[b].sum() / sigma ** 2
            for j in range(len(lm)):
                if not judged[j]:
                    continue
                cost[rows[j]] = BIG
                if agree[j] and best[j] >= 0:
                    if strong:
                        cost[:, best[j]] = BIG
                        cost[rows[j], best[j]] = 0.0
                    else:
                        cost[rows[j], best[j]] = fit_cost
            # a point that the module's best fit and every rival as close place on one
            # of its markers is the module's, even when they disagree on which one, unless
            # a marker outside the module fits it better on its own
            rivals = hyps[near | (np.arange(H) == b)]
            outside = np.ones(len(cost), bool)
            outside[rows] = False
            for q in used:
                if (rivals == q).any(1).all():
                    cost[outside & (cost[:, q] >= fit_cost), q] = BIG

    def _commit(self, cur: np.ndarray, has: np.ndarray, steps: int = 1) -> None:
        seen_prev = has & (self.age == 0)
        if len(self.modules):
            steady_now = seen_prev[self.mod_idx] | ~self.mod_mask
            full = steady_now.all(1)
            if self._mod_fit_now is not None:
                known = (np.isfinite(self.mod_shape).all(2) | ~self.mod_mask).all(1)
                full &= self._mod_fit_now | ~known
            self._mod_fit_now = None
            if full.any():
                self.mod_shape[full] = np.where(self.mod_mask[full, :, None],
                                                cur[self.mod_idx[full]], np.nan)
                new = full & ~(np.isfinite(self.mod_shape_first).all(2) | ~self.mod_mask).all(1)
                self.mod_shape_first[new] = self.mod_shape[new]
        if self.compiled:
            kern.commit_state(cur, has, self.pos, self.vel, self.age, self.snap,
                              self.since_reacquired, self.nb, float(self.smooth), steps)
        else:
            self._commit_state(cur, has, seen_prev, steps)
        if self.adapt > 0 and has.sum() > 3 and self.frames % 4 == 0:
            self._learn_distances(cur, min(1.0, 4 * self.adapt))
        self.frames += 1

    def _commit_state(self, cur: np.ndarray, has: np.ndarray, seen_prev: np.ndarray,
                      steps: int) -> None:
        """numpy twin of label_kernels.commit_state."""
        newvel = np.where(seen_prev[:, None], (cur - self.pos) / steps, 0.0)
        self.vel = np.where(seen_prev[:, None], self.smooth * newvel + (1 - self.smooth) * self.vel,
                            np.where(has[:, None], 0.0, self.vel))
        # a reacquired marker takes its neighbours' velocity
        re = has & ~seen_prev
        self.since_reacquired = np.where(re, 0, self.since_reacquired + steps)
        if re.any():
            nbv = self.vel[self.nb[re]]
            ok = has[self.nb[re]]
            self.vel[re] = (nbv * ok[:, :, None]).sum(1) / np.maximum(ok.sum(1), 1)[:, None]
        # a marker's snapshot (where everything was when it was last seen) is only renewed
        # once it has been seen twice in a row: a one-frame ghost must not move it
        steady = seen_prev | (has & ~np.isfinite(self.snap[np.arange(self.n),
                                                              np.arange(self.n)]).all(1))
        self.vel[~np.isfinite(self.vel).all(1)] = 0.0
        self.pos = np.where(has[:, None], cur, self.pos)
        self.age = np.where(has, 0, self.age + steps)
        if steady.any():
            self.snap[steady] = cur[None]


# ---------------------------------------------------------------------- rigid modules


def _duplicates(P: np.ndarray, within_m: float) -> np.ndarray | None:
    """For each point the first point within `within_m` of it (itself if none, and
    chains followed to their first point); None when no two points are that close."""
    k = len(P)
    if k < 2 or within_m <= 0:
        return None
    diff = P[:, None] - P[None]
    close = np.einsum("abi,abi->ab", diff, diff) < within_m * within_m
    close[np.tril_indices(k)] = False
    if not close.any():
        return None
    close[np.diag_indices(k)] = True
    rep = np.argmax(close, axis=0)                 # the first close point, or itself
    for _ in range(k):
        nxt = rep[rep]
        if np.array_equal(nxt, rep):
            break
        rep = nxt
    return rep


def _module_candidates(lm_all, mates_all, cur, Pf, mean_all, tol_all, cand):
    """numpy twin of label_kernels.module_candidates."""
    seen = np.isfinite(cur).all(1)
    mates = mates_all[lm_all] & seen[None]                               # (l, n)
    cand = cand.copy()
    two = mates.sum(1) >= 2
    if two.any():
        xs = np.where(np.isnan(cur), 0.0, cur)
        d = np.sqrt(((Pf[:, None] - xs[None]) ** 2).sum(2))              # (F, n)
        lt = lm_all[two]
        off = np.abs(d[None] - mean_all[lt][:, None]) > tol_all[lt][:, None]
        cand[two] |= ~(off & mates[two][:, None]).any(2)
    return cand


def _swap_scores(cur, i, j, swap_w, mean_all, witness):
    """numpy twin of label_kernels.swap_scores."""
    x = np.nan_to_num(cur)
    seen = np.isfinite(cur).all(1) & witness
    di = np.linalg.norm(cur[i][:, None] - x[None], axis=2)       # (p, n)
    dj = np.linalg.norm(cur[j][:, None] - x[None], axis=2)
    wi = swap_w[i] * seen[None]
    wj = swap_w[j] * seen[None]
    wi[np.arange(len(i)), j] = 0
    wj[np.arange(len(j)), i] = 0
    mi, mj = mean_all[i], mean_all[j]
    keep = (wi * (di - mi) ** 2 + wj * (dj - mj) ** 2).sum(1)
    swap = (wi * (dj - mi) ** 2 + wj * (di - mj) ** 2).sum(1)
    return keep, swap


def _injective_product(options: list[np.ndarray]) -> np.ndarray:
    """All combinations (one entry per list, -1 = none) that use no point twice."""
    grids = np.meshgrid(*options, indexing="ij")
    h = np.stack([g.ravel() for g in grids], axis=1)
    ok = np.ones(len(h), bool)
    for a in range(h.shape[1]):
        for b in range(a + 1, h.shape[1]):
            ok &= (h[:, a] != h[:, b]) | (h[:, a] < 0)
    return h[ok]


# ---------------------------------------------------------------------- from scratch


SUBJECT_REL = 0.15   # another body: distances differ by this fraction (1 SD) at least


def _tolerance(ms: MarkerSet, noise_m: float = 0.003) -> np.ndarray:
    subject = np.maximum(ms.subject_sd_m, SUBJECT_REL * ms.mean_m)
    return 3.0 * np.sqrt(ms.sd_m ** 2 + subject ** 2 + 2 * noise_m ** 2) + 0.006


def _match_segment(P: np.ndarray, D: np.ndarray, members: list[int], ms: MarkerSet,
                   tol: np.ndarray, free: np.ndarray, limit: int = 64) -> list:
    """All assignments of `members` to free points whose pairwise distances fit, best
    first (backtracking over the gated pair table)."""
    m = len(members)
    mean = ms.mean_m[np.ix_(members, members)]
    tl = tol[np.ix_(members, members)]
    out: list[tuple[float, list[int]]] = []
    cand = np.nonzero(free)[0]

    def rec(chosen: list[int], cost: float) -> None:
        if len(out) > 4 * limit:
            return
        i = len(chosen)
        if i == m:
            out.append((cost, list(chosen)))
            return
        c = cand[~np.isin(cand, chosen)]
        if i:
            e = np.abs(D[np.ix_(chosen, c)] - mean[:i, i:i + 1]) / tl[:i, i:i + 1]
            ok = (e <= 1.0).all(0)
            c, e = c[ok], e[:, ok]
            costs = (e ** 2).sum(0)
        else:
            costs = np.zeros(len(c))
        for j, cc in zip(c, costs, strict=True):
            rec([*chosen, int(j)], cost + float(cc))

    rec([], 0.0)
    out.sort(key=lambda t: t[0])
    return out[:limit]


def initial_labels(P: np.ndarray, ms: MarkerSet, n_hypotheses: int = 24,
                   n_segments: int = 2, return_cost: bool = False):
    """Label one frame from the marker set alone: the steadiest multi-marker segment is
    matched by its distances (every fitting assignment is a hypothesis), the others grow
    from it by their distances to labelled markers, and the handedness checks (signed
    volumes) pick between a body and its mirror image. Returns a label per point (-1:
    ghost or unknown)."""
    P = np.asarray(P, float)
    k = len(P)
    lab = np.full(k, -1)
    if k < 3:
        return (lab, np.inf) if return_cost else lab
    D = np.linalg.norm(P[:, None] - P[None], axis=2)
    tol = _tolerance(ms)
    order = sorted([s for s in ms.segments if len(s.markers) >= 3],
                   key=lambda s: (-len(s.markers), s.spread_m))
    best = None
    for seg in order[:n_segments]:
        hyps = _match_segment(P, D, seg.markers, ms, tol, np.ones(k, bool),
                              limit=n_hypotheses)
        for _, chosen in hyps:
            marker_point = np.full(ms.n, -1)
            marker_point[seg.markers] = chosen
            cost = _grow(P, D, ms, tol, marker_point)
            votes = _chirality(P, ms, marker_point)
            n_missing = int((marker_point < 0).sum())
            total = cost + 9.0 * n_missing - 3.0 * votes
            if best is None or total < best[0]:
                best = (total, marker_point)
    if best is None:
        return (lab, np.inf) if return_cost else lab
    mp = order_modules(P, ms, best[1].copy())
    got = mp >= 0
    lab[mp[got]] = np.nonzero(got)[0]
    return (lab, best[0]) if return_cost else lab


def _grow(P: np.ndarray, D: np.ndarray, ms: MarkerSet, tol: np.ndarray,
          marker_point: np.ndarray) -> float:
    """Label the rest one marker at a time: each step takes the unlabelled marker whose
    best point (by its distances to every labelled marker, weighted by how steady each
    distance is) stands out most clearly from its second best."""
    total = 0.0
    k = len(P)
    w_all = 1.0 / tol ** 2
    while True:
        todo = np.nonzero(marker_point < 0)[0]
        done = np.nonzero(marker_point >= 0)[0]
        if not len(todo) or not len(done):
            break
        used = np.zeros(k, bool)
        used[marker_point[done]] = True
        free = np.nonzero(~used)[0]
        if not len(free):
            break
        d = D[np.ix_(free, marker_point[done])]                       # (F, L)
        mu = ms.mean_m[np.ix_(todo, done)]                            # (T, L)
        w = w_all[np.ix_(todo, done)]
        e2 = np.minimum((d[None] - mu[:, None]) ** 2 * w[:, None] * 9.0, 16.0)  # (T, F, L)
        cost = (e2 * w[:, None]).sum(2) / w.sum(1)[:, None]          # weighted mean chi2/9
        if cost.shape[1] >= 2:
            part = np.partition(cost, 1, axis=1)
            best, second = part[:, 0], part[:, 1]
        else:
            best, second = cost[:, 0], np.full(len(todo), 16.0)
        ok = best < 9.0
        if not ok.any():
            break
        margin = np.where(ok, second - best, -np.inf)
        t = int(np.argmax(margin))
        marker_point[todo[t]] = free[int(np.argmin(cost[t]))]
        total += float(best[t])
    return total


def _initial_as_one(P: np.ndarray, ms: MarkerSet, merge_m: float) -> tuple[np.ndarray, float]:
    """initial_labels (with its cost) with points closer than `merge_m` labelled as one."""
    rep = _duplicates(P, merge_m)
    if rep is None:
        return initial_labels(P, ms, return_cost=True)
    keep = np.nonzero(rep == np.arange(len(P)))[0]
    lab, cost = initial_labels(P[keep], ms, return_cost=True)
    row = np.full(len(P), -1)
    row[keep] = np.arange(len(keep))
    return lab[row[rep]], cost


def _chirality(P: np.ndarray, ms: MarkerSet, marker_point: np.ndarray) -> int:
    """Votes for this labelling's handedness matching the marker set's (+) or its mirror."""
    if not len(ms.chiral):
        return 0
    ok = (marker_point[ms.chiral] >= 0).all(1)
    if not ok.any():
        return 0
    x = np.full((ms.n, 3), np.nan)
    got = marker_point >= 0
    x[got] = P[marker_point[got]]
    v = signed_volume(x, ms.chiral[ok])
    return int((np.sign(v) == ms.chiral_sign[ok]).sum() - (np.sign(v) != ms.chiral_sign[ok]).sum())


# ---------------------------------------------------------------------- a whole take


def label_take(points: Points, ms: MarkerSet, rate_hz: float = 120.0,
               seed: Take | None = None, seed_frames: int = 0, progress=None,
               options: dict | None = None, start_frames: int = 10
               ) -> tuple[Take, np.ndarray, np.ndarray]:
    """Label every frame of `points`. Returns the labelled take, per-frame confidence
    (mean over labelled markers) and the per-point labels (aligned with points rows after
    sorting by frame, see `Points.split`)."""
    frames, per_frame = points.split()
    lab = Labeller(ms, rate_hz, **(options or {}))
    n_frames = int(frames[-1] - frames[0] + 1) if len(frames) else 0
    first = int(frames[0]) if len(frames) else 0
    xyz = np.full((n_frames, ms.n, 3), np.nan)
    conf = np.zeros(n_frames)
    labels_out = []
    start = 0
    if seed is not None and seed_frames > 0:
        s = seed.select(ms.labels)
        use = min(seed_frames, s.n_frames)
        sx = s.xyz_m[:use]
        lab.seed_take(sx)
        fidx = np.arange(use) + s.first_frame - first
        keep = (fidx >= 0) & (fidx < n_frames)
        xyz[fidx[keep]] = sx[keep]
        conf[fidx[keep]] = 1.0
        start = int(np.searchsorted(frames, s.first_frame + use))
        for f in range(start):
            labels_out.append(np.full(len(per_frame[f]), -2))
    order = list(range(start, len(frames)))
    out: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    if start == 0 and len(frames) and start_frames > 1:
        # from the marker set alone: one global assignment on a window of frames
        # (daemon/markers/label_start.py), handed to the tracker as labelled start frames, then
        # tracked forward from the window's end and backward from its start
        w0, wl, wx = window_start(per_frame, ms, noise_m=lab.noise_m,
                                  merge_m=lab.merge_m)
        # the tracker learns this body's distances and shapes from the whole window,
        # then labels the window itself from its first two frames (markers the start
        # left out, e.g. hidden for most of the window, are found on the way)
        lab.seed_take(wx)
        S = min(2, len(wl))
        lab.seed(wx[0])
        if S > 1:
            lab.update_labelled(wx[1])
        for w in range(S):
            out[w0 + w] = (wl[w], np.where(wl[w] >= 0, 0.5, 0.0))
        order = list(range(w0 + S, len(frames)))
        if w0 > 0:
            back = Labeller(ms, rate_hz, **(options or {}))
            back.seed_take(wx[::-1])
            for i in range(w0 - 1, -1, -1):
                out[i] = back.update(per_frame[i])
    for n_done, i in enumerate(order):
        out[i] = lab.update(per_frame[i])
        if progress is not None and n_done % 200 == 0:
            progress.update(n_done)
    for i in range(start, len(frames)):
        P = per_frame[i]
        m, c = out[i]
        fi = int(frames[i] - first)
        got = m >= 0
        xyz[fi, m[got][::-1]] = P[got][::-1]      # a duplicate: its first point
        conf[fi] = float(c[got].mean()) if got.any() else 0.0
        labels_out.append(m)
    take = Take(list(ms.labels), xyz, rate_hz, first)
    return take, conf, labels_out


def duplicate_trajectories(take: Take, within_m: float = 0.006, share: float = 0.9
                           ) -> list[tuple[str, str, int]]:
    """Pairs of a file's trajectories that are one marker stored twice: within
    `within_m` of each other in at least `share` of the frames both are seen (and in at
    least 3 frames). Returns (name, twin, frames together) for each pair."""
    x = take.xyz_m
    out = []
    for i in range(len(take.labels)):
        d = np.linalg.norm(x[:, i + 1:] - x[:, i:i + 1], axis=2)       # (F, n - i - 1)
        both = np.isfinite(d).sum(0)
        close = (d < within_m).sum(0)
        for j in np.nonzero((both >= 3) & (close >= share * np.maximum(both, 1)))[0]:
            out.append((take.labels[i], take.labels[i + 1 + j], int(both[j])))
    return out


def merged_points(labels_per_frame: list[np.ndarray]) -> int:
    """Points labelled as a marker another point of their frame already is (duplicates
    taken as one)."""
    return int(sum(int((m >= 0).sum()) - len(np.unique(m[m >= 0])) for m in labels_per_frame))


# ---------------------------------------------------------------------- scoring on truth


def hide_spans(take: Take, fraction: float, span_s: tuple[float, float] = (0.1, 1.0),
               seed: int = 0) -> Take:
    """A copy with random spans hidden until `fraction` of marker-frames are gone."""
    rng = np.random.default_rng(seed)
    xyz = take.xyz_m.copy()
    F, n = xyz.shape[:2]
    hidden = np.zeros((F, n), bool)
    target = fraction * F * n
    lo, hi = (max(1, int(round(v * take.rate_hz))) for v in span_s)
    while hidden.sum() < target:
        m = rng.integers(n)
        L = int(rng.integers(lo, hi + 1))
        s = int(rng.integers(0, max(1, F - L)))
        hidden[s:s + L, m] = True
    xyz[hidden] = np.nan
    return Take(list(take.labels), xyz, take.rate_hz, take.first_frame)


def points_with_ghosts(take: Take, ghosts_per_frame: int, seed: int = 0
                       ) -> tuple[Points, np.ndarray]:
    """Unlabelled, shuffled points of a take plus uniform ghost points in each frame's
    marker bounding box (grown by 0.1 m). Returns the points and each point's true marker
    index (-1 for ghosts)."""
    rng = np.random.default_rng(seed)
    vis = take.visible
    fr, mk = np.nonzero(vis)
    xyz = take.xyz_m[fr, mk]
    F = take.n_frames
    if ghosts_per_frame:
        lo = np.nanmin(take.xyz_m, axis=1) - 0.1
        hi = np.nanmax(take.xyz_m, axis=1) + 0.1
        gf = np.repeat(np.arange(F), ghosts_per_frame)
        g = lo[gf] + rng.random((len(gf), 3)) * (hi[gf] - lo[gf])
        ok = np.isfinite(g).all(1)
        fr = np.concatenate([fr, gf[ok]])
        mk = np.concatenate([mk, np.full(ok.sum(), -1)])
        xyz = np.concatenate([xyz, g[ok]])
    order = np.argsort(fr + rng.random(len(fr)))
    return Points(fr[order] + take.first_frame, xyz[order]), mk[order]


def score(points: Points, truth_marker: np.ndarray, labels_per_frame: list[np.ndarray],
          start_frame_index: int = 0) -> dict:
    """Fraction of real marker-points labelled correctly, and of ghosts left unlabelled,
    counted from the frame index `start_frame_index` (after any seed frames)."""
    order = np.argsort(points.frame, kind="stable")
    tm = truth_marker[order]
    f = points.frame[order]
    _, starts = np.unique(f, return_index=True)
    tm_split = np.split(tm, starts[1:])
    got = np.concatenate(labels_per_frame[start_frame_index:])
    want = np.concatenate(tm_split[start_frame_index:])
    real = want >= 0
    return {"marker_frames": int(real.sum()),
            "correct": float((got[real] == want[real]).mean()) if real.any() else 1.0,
            "unlabelled": float((got[real] < 0).mean()) if real.any() else 0.0,
            "ghosts": int((~real).sum()),
            "ghosts_rejected": float((got[~real] < 0).mean()) if (~real).any() else 1.0}
