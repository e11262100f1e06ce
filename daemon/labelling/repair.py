"""Structure checks and swap repairs of a frame's labels, for the labeller (labeller.py).

Tracking carries a wrong labelling on as faithfully as a right one, so after each
frame's assignment the labels are checked: a rigid module whose points no longer fit its
shape is put in the order of its points that fits best (labels rotated within a foot, a
wrist pair swapped), two close markers whose distances to everyone fit much better the
other way round are swapped, and (optionally) a swap witness tetrahedron turned inside
out or a segment's order against its shape. The module check also decides which
modules fit well enough for their shape to be renewed from this frame.
"""

from __future__ import annotations

from itertools import permutations

import numpy as np

from daemon.labelling.markerset import signed_volume
from daemon.labelling.modules import rigid_residuals


class StructureRepair:
    """Per-frame structure checks and repairs (a part of `Labeller`)."""

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
        # three points of a module cannot tell it from its mirror image (a triangle fits
        # either way round) and a shape learned in one posture may fit the mirror better:
        # markers tracked without a break since long (their tracks' own evidence) keep
        # their names unless four or more points speak (on one body the pelvis's three
        # seen markers were mirrored so, through 47 frames, from a start of 10 frames)
        moved = new_member != held
        if len(held) < 4 and (self.since_reacquired[idx[held[moved]]]
                              >= self.suspect_frames).any():
            return False
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
            return self.kern.rigid_residuals(np.ascontiguousarray(np.broadcast_to(shape, X.shape)),
                                        np.ascontiguousarray(X), np.ascontiguousarray(w),
                                        True)
        return rigid_residuals(shape, X, w, True)

    def _maps(self, m: int, p: int) -> np.ndarray:
        key = (m, p)
        if key not in self._maps_cache:
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
        scores = self.kern.swap_scores if self.compiled else swap_scores_numpy
        # a marker found again in this very frame (perhaps a ghost) is no witness
        keep, swap = scores(cur, i, j, self.swap_w, self.mean_all, ~self._new_now)
        better = (swap < 0.25 * keep) & (keep - swap > 25.0)
        for a, b in zip(i[better], j[better], strict=True):
            if point_of[a] < 0 or point_of[b] < 0:
                continue
            if self._new_now[a] != self._new_now[b] and (
                    np.linalg.norm(cur[a] - cur[b]) > self.gate_m):
                # one was found again in this frame, the other followed its own motion to a
                # point farther than the tracking gate from the new one's: tracking cannot
                # have mixed them up, so the new one's point (a ghost, or another marker)
                # is what fits badly; it is let go, the tracked one keeps its point
                new = a if self._new_now[a] else b
                marker_of[point_of[new]] = -1
                point_of[new] = -1
                cur[new] = np.nan
                self._new_now[new] = False
                done = True
                continue
            pa, pb = point_of[a], point_of[b]
            point_of[a], point_of[b] = pb, pa
            marker_of[pa], marker_of[pb] = b, a
            cur[[a, b]] = cur[[b, a]]
            self.pos[[a, b]] = self.pos[[b, a]]
            self.vel[[a, b]] = self.vel[[b, a]]
            done = True
        return done


def swap_scores_numpy(cur, i, j, swap_w, mean_all, witness):
    """numpy twin of kernels.swap_scores."""
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
