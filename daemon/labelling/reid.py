"""Re-identifying a rigid module's lost markers jointly, for the labeller (labeller.py).

Marker by marker, two markers at equal distances from the visible ones (a foot's 5th
metatarsal and toe from its heel and ankle) or a ghost that fits one marker's distances
can take the wrong point, and a module hidden whole (a forearm, a foot) is not found at
all: after the arm swung its markers' predictions are tens of centimetres off. A proper
rigid fit of the module's shape (this take's, or the set's with its handedness) to
every assignment of its lost markers to candidate points tells; the winner is forced
into the frame's assignment cost, a tie waits for more of the module to show.
"""

from __future__ import annotations

import numpy as np

from daemon.labelling.modules import pair_distances
from daemon.labelling.neighbours import BIG


class ModuleReidentification:
    """Joint re-identification of rigid modules (a part of `Labeller`)."""

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
        hyps = injective_product(options)
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
            cand_all = self.kern.module_candidates(lm_all, self.mates, cur, Pf, self.mean_all,
                                              self.adapt_tol, cand_all)
        else:
            cand_all = module_candidates_numpy(lm_all, self.mates, cur, Pf, self.mean_all,
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
            hyps = injective_product([np.r_[-1, np.nonzero(c)[0]] for c in cand])
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
            # the best fit leaving out the one marker lost (a finger bent against its
            # hand's shape, the rest fitting it badly) does not veto it where the fit with
            # it added on a point of its own gate places it within the fit's allowance:
            # its own prediction and neighbours decide (with two lost, a foot's toe and
            # 5th metatarsal, the fit must tell which is which)
            for j in range(len(lm)):
                if not judged[j]:
                    continue
                if best[j] < 0 and len(lm) == 1:
                    fits = (r2[:, pos[j]] <= (3.5 * sigma) ** 2) & got[:, j]
                    if (fits & own[j, np.maximum(hyps[:, j], 0)]).any():
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


def module_candidates_numpy(lm_all, mates_all, cur, Pf, mean_all, tol_all, cand):
    """numpy twin of kernels.module_candidates."""
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


def injective_product(options: list[np.ndarray]) -> np.ndarray:
    """All combinations (one entry per list, -1 = none) that use no point twice."""
    grids = np.meshgrid(*options, indexing="ij")
    h = np.stack([g.ravel() for g in grids], axis=1)
    ok = np.ones(len(h), bool)
    for a in range(h.shape[1]):
        for b in range(a + 1, h.shape[1]):
            ok &= (h[:, a] != h[:, b]) | (h[:, a] < 0)
    return h[ok]
