"""Labelling unlabelled 3D points with a marker set, frame by frame: the tracker.

Every labelled marker is tracked: predicted from its velocity and assigned to the
nearest point by one global assignment (Hungarian), checked against its steadiest
neighbours' distances (which rejects ghosts and swaps), and a marker that was lost is
predicted from its neighbours' rigid motion since it was last seen (the shape carried
along), so it is re-identified when it reappears. A marker set's distances alone match a
module of a frame in many ways; tracking carries one consistent labelling through the
take instead, and the checks below catch where it goes wrong.

The stages live beside this module: what the neighbours say about a marker and a
point (neighbours), rigid modules found again jointly (reid), the structure
checks and swap repairs (repair), a frame labelled from the set alone
(single), the window start (start) and a whole take (offline).

Live use (one frame at a time, e.g. in the daemon's pipeline):

    lab = Labeller(markerset, rate_hz=120)
    lab.start_from_labelled(xyz)       # optional: a labelled frame (n, 3), NaN = unseen
    labels, confidence = lab.update(points_xyz)   # (k,) marker index or -1, (k,) 0..1
    lab.positions                      # (n, 3) current labelled positions, NaN = not seen

Without a labelled frame the first update labels the frame from the marker set alone.
"""

from __future__ import annotations

import warnings

import numpy as np

from calibkit.core.assignment import linear_sum_assignment
from daemon.labelling.markerset import MarkerSet
from daemon.labelling.modules import module_template, rigid_modules, template_sigma
from daemon.labelling.neighbours import BIG, NeighbourEvidence
from daemon.labelling.reid import ModuleReidentification
from daemon.labelling.repair import StructureRepair
from daemon.labelling.single import SUBJECT_REL, initial_labels, template_tolerance

K_NEIGHBOURS = 6


def compiled_kernels():
    """The labeller's numba kernels (daemon/labelling/kernels.py), imported when a
    Labeller first uses them: loading numba and the cached kernels costs about 0.3-0.6 s
    of CPU, more than their numpy twins lose on a take of a few thousand frames."""
    from daemon.labelling import kernels as label_kernels  # deferred on purpose: loads numba

    return label_kernels


class Labeller(NeighbourEvidence, ModuleReidentification, StructureRepair):
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
                 merge_m: float | None = None, own_spread: bool = False) -> None:
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
        # this body's own spread of each distance (n, n), from this take (learn_spread)
        self.own_sd = np.zeros((n, n))
        self.nb_own_sd = np.zeros(self.nb.shape)
        self._own_wider = False
        # learn it (options={"own_spread": True}, with a labelled start only: from the set
        # alone the labels are the set's guess, and a spread learned from a window it got
        # wrong loosens the checks that catch it). Off by default: over 42 bodies it
        # gained three and cost three (docs/labelling_subjects.md, round 6)
        self.own_spread = own_spread
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
        self.adapt_tol = template_tolerance(markerset, noise_m)
        # segment shapes for the order check: the marker set's, replaced by this take's
        from itertools import permutations
        self.seg_checks = [(np.array(sg.markers), sg.shape_m.copy(),
                            np.array(list(permutations(range(len(sg.markers))))))
                           for sg in markerset.segments if 3 <= len(sg.markers) <= 5]
        self.shape_check = shape_check
        self.template_tol = template_tolerance(markerset, noise_m)
        self.anchors = np.argsort(sd, axis=1)[:, :-1]     # all others, steadiest first
        # rigid modules (a segment and the markers that hold still with it, e.g. a foot's
        # tetrahedron with its ankle): re-identified jointly, by a proper rigid fit of the
        # module's own shape in this take (which tells a module from its mirror image)
        self.module_reid = module_reid
        self.chi2_cost = chi2_cost
        self.renew_sigma = renew_sigma
        self.compiled = compiled       # numba kernels (kernels); numpy twins otherwise
        self.kern = compiled_kernels() if compiled else None
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
            return self._tol_cache          # known_frames only change in _commit/start_*
        self._tol_frames = self.frames
        known = self.known_frames >= 30
        if self._tol_known is not None and np.array_equal(known, self._tol_known):
            return self._tol_cache
        both = known[:, None] & known[self.nb]
        subject = np.where(both, 0.0, self.nb_subject)
        self._tol_known = known
        self._tol_cache = 3.0 * np.sqrt(self.nb_sd ** 2 + subject ** 2
                                        + 2 * self.noise_m ** 2) + 0.004
        self._own_wider = bool((self.nb_own_sd > self.nb_sd).any())
        sd = np.maximum(self.nb_sd, self.nb_own_sd)
        self._cand_tol_cache = 3.0 * np.sqrt(sd ** 2 + subject ** 2
                                             + 2 * self.noise_m ** 2) + 0.004
        return self._tol_cache

    def start_from_labelled(self, xyz: np.ndarray) -> None:
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

    def start_from_labelled_frames(self, xyz: np.ndarray) -> None:
        """Start from several labelled frames (f, n, 3): distances from all of them."""
        d = np.linalg.norm(xyz[:, :, None] - xyz[:, None], axis=3)  # (f, n, n)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            med = np.nanmedian(d, axis=0)
        self.mean_all = np.where(np.isfinite(med), med, self.mean_all)
        seen = np.isfinite(xyz).all(2).any(0)
        self.known_frames[seen] = 10 ** 6
        self._tol_frames = -1
        # pairs seen in the labelled frames: this body's distances, known; pairs not seen
        # (a marker hidden throughout): the set's, as loose as another subject's
        self.adapt_tol = np.where(np.isfinite(med), 3.0 * np.sqrt(
            self.ms.sd_m ** 2 + 2 * self.noise_m ** 2) + 0.004,
            template_tolerance(self.ms, self.noise_m))
        self.nb_mean = self.mean_all[np.arange(self.n)[:, None], self.nb]
        self.adapted = True
        self.learn_spread(xyz)        # (a window's worth: a few start frames show none)
        for k, (idx, _, perms) in enumerate(self.seg_checks):
            full = np.isfinite(xyz[:, idx]).all(axis=(1, 2))
            if full.any():
                shape = xyz[np.nonzero(full)[0][-1]][idx]
                self.seg_checks[k] = (idx, shape - shape.mean(0), perms)
        if len(xyz) >= 2:
            self.start_from_labelled(xyz[-2])
            self.update_labelled(xyz[-1])
        else:
            self.start_from_labelled(xyz[-1])

    def start(self, points: np.ndarray, labels: np.ndarray) -> None:
        """Start from one frame's points and their labels (-1 = none)."""
        P = np.asarray(points, float).reshape(-1, 3)
        cur = np.full((self.n, 3), np.nan)
        got = labels >= 0
        cur[labels[got]] = P[got]
        self._commit(cur, np.isfinite(cur).all(1))

    def update_labelled(self, xyz: np.ndarray) -> None:
        """Advance the tracker with a frame whose labels are known (labelled start frames)."""
        ok = np.isfinite(xyz).all(1)
        self._commit(np.where(ok[:, None], xyz, np.nan), ok)

    def take_state(self, other: Labeller) -> None:
        """Carry on as `other` (a tracker started again from a window that verification
        relabelled): everything it knows replaces what this one knew."""
        vars(self).clear()
        vars(self).update(vars(other))

    def relabel(self, perm: np.ndarray) -> None:
        """Rename the tracked markers: marker i becomes perm[i] (-1: it is dropped), with
        everything the tracker learned about it (its motion, its snapshot, the take's
        distances to the others), when a verification found the labels wrong. Modules
        whose members changed learn their shape again."""
        n = self.n
        src = np.full(n, -1)
        keep = perm >= 0
        src[perm[keep]] = np.nonzero(keep)[0]
        has = src >= 0
        s0 = np.maximum(src, 0)
        self.pos = np.where(has[:, None], self.pos[s0], np.nan)
        self.vel = np.where(has[:, None], self.vel[s0], 0.0)
        self.age = np.where(has, self.age[s0], 10 ** 6)
        snap = self.snap[s0][:, s0]
        snap[~has] = np.nan
        snap[:, ~has] = np.nan
        self.snap = np.ascontiguousarray(snap)
        changed = src != np.arange(n)
        self.since_reacquired = np.where(changed, 0, self.since_reacquired)
        pair = has[:, None] & has[None]
        self.mean_all = np.where(pair, self.mean_all[s0][:, s0], self.ms.mean_m)
        self.adapt_tol = np.where(pair, self.adapt_tol[s0][:, s0],
                                  template_tolerance(self.ms, self.noise_m))
        self.known_frames = np.where(has, self.known_frames[s0], 0)
        self.nb_mean = self.mean_all[np.arange(n)[:, None], self.nb]
        self.own_sd = np.where(pair, self.own_sd[s0][:, s0], 0.0)
        self.nb_own_sd = self.own_sd[np.arange(n)[:, None], self.nb]
        if len(self.modules):
            hit = (changed[self.mod_idx] & self.mod_mask).any(1)
            self.mod_shape[hit] = np.nan
            self.mod_shape_first[hit] = np.nan
        self._tol_frames = -1
        self._tol_known = None

    def found(self, markers: np.ndarray, xyz: np.ndarray, vel: np.ndarray,
              age: np.ndarray | None = None, snap: np.ndarray | None = None) -> None:
        """Markers (m,) that a verification found on points tracking had left unlabelled,
        last seen at xyz (m, 3) moving by vel (m, 3) a frame, `age` (m,) frames ago (0:
        now) with everything where `snap` (m, n, 3) had it then (default: where the
        tracker has it now): tracked, or looked for from their neighbours' motion since,
        from here on."""
        self.pos[markers] = xyz
        self.vel[markers] = vel
        self.age[markers] = 0 if age is None else age
        self.since_reacquired[markers] = 0
        if snap is None:
            snap = np.where((self.age == 0)[:, None], self.pos, np.nan)[None]
        self.snap[markers] = snap
        self.snap[markers, markers] = xyz

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
        rep = duplicates(P, self.merge_m)
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
            # (a candidate is possible within the body's own spread; the set's ranks them)
            cost[(dist > gate[:, None]) | (self._cand_veto > self.candidate_limit)] = BIG
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
            self.kern.commit_state(cur, has, self.pos, self.vel, self.age, self.snap,
                              self.since_reacquired, self.nb, float(self.smooth), steps)
        else:
            self._commit_state(cur, has, seen_prev, steps)
        if self.adapt > 0 and has.sum() > 3 and self.frames % 4 == 0:
            self._learn_distances(cur, min(1.0, 4 * self.adapt))
        self.frames += 1

    def _commit_state(self, cur: np.ndarray, has: np.ndarray, seen_prev: np.ndarray,
                      steps: int) -> None:
        """numpy twin of kernels.commit_state."""
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


def duplicates(P: np.ndarray, within_m: float) -> np.ndarray | None:
    """For each point the first point within `within_m` of it (itself if none, and
    chains followed to their first point); None when no two points are that close."""
    k = len(P)
    if k < 2 or within_m <= 0:
        return None
    diff = P[:, None] - P[None]
    close = np.einsum("abi,abi->ab", diff, diff) < within_m * within_m
    if close.sum() == k:                   # only each point itself (the common case)
        return None
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
