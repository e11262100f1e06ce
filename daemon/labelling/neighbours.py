"""What a marker's neighbours say about it, for the labeller (daemon/labelling/labeller.py).

A point is a marker's when its distances to the marker's steadiest labelled neighbours
fit the set (or this take's own distances, once learned): that rejects a ghost or a swap
that the nearest-point assignment took. A lost marker is looked for where the rigid
motion of the markers that keep their distance to it has carried it since it was last
seen, and one never seen is found by its distances to every labelled marker. Each of
these has a compiled kernel (kernels) and the numpy twin here.
"""

from __future__ import annotations

import numpy as np

BIG = 1e6


class NeighbourEvidence:
    """Per-frame costs from the neighbours (a part of `Labeller`; it holds the state)."""

    def _structure_error(self, cur: np.ndarray) -> np.ndarray:
        """Per marker: mean over its labelled neighbours of |d - mean| / tolerance (each
        capped at 3, so one bad neighbour cannot condemn a marker alone)."""
        if self.compiled:
            return self.kern.structure_error(cur, self.nb, self.nb_mean, self._tol())
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
            return self.kern.fresh_cost(markers, P, cur, self.anchors, self.adapt_tol,
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
            mean, num, self._cand_chi2 = self.kern.candidate_error(
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
            pred, self._support_spread = self.kern.predict_from_neighbours(
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
