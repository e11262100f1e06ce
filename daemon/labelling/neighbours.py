"""What a marker's neighbours say about it, for the labeller (daemon/labelling/labeller.py).

A point is a marker's when its distances to the marker's steadiest labelled neighbours
fit the set (or this take's own distances, once learned): that rejects a ghost or a swap
that the nearest-point assignment took. A lost marker is looked for where the rigid
motion of the markers that keep their distance to it has carried it since it was last
seen, and one never seen is found by its distances to every labelled marker. Each of
these has a compiled kernel (kernels) and the numpy twin here.
"""

from __future__ import annotations

import warnings

import numpy as np

BIG = 1e6
SPREAD_FRAMES = 30       # a pair seen together this many frames of a window: its spread


class NeighbourEvidence:
    """Per-frame costs from the neighbours (a part of `Labeller`; it holds the state)."""

    def learn_spread(self, xyz: np.ndarray, min_frames: int = SPREAD_FRAMES) -> None:
        """Learn how much this body moves each distance from a labelled window (W, n, 3)
        of this take (labelled start frames, then each window tracked on from them:
        verify_take.Verification), where the take has a labelled start (`own_spread`;
        from the set alone the labels are the set's guess): per pair seen together in
        `min_frames` frames or more, the robust SD (1.4826 median absolute deviation: a few
        mislabelled frames do not widen it) of its distance over the window; the largest
        any window showed is kept. Ten labelled start frames (a twelfth of a second) show
        next to none of a shoulder's spread; the windows tracked after them do. Where the
        body's spread is wider than the set's it decides whether a lost marker's
        candidate point is possible at all (`_cand_tol`)."""
        xyz = np.asarray(xyz, float)
        if not self.own_spread or len(xyz) < min_frames or xyz.shape[1] != self.n:
            return
        d = np.linalg.norm(xyz[:, :, None] - xyz[:, None], axis=3)        # (W, n, n)
        enough = np.isfinite(d).sum(0) >= min_frames
        if not enough.any():
            return
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            med = np.nanmedian(d, axis=0)
            mad = np.nanmedian(np.abs(d - med), axis=0)
        sd = np.where(enough, 1.4826 * mad, 0.0)
        np.fill_diagonal(sd, 0.0)
        self.own_sd = np.maximum(self.own_sd, sd)
        self.nb_own_sd = self.own_sd[np.arange(self.n)[:, None], self.nb]
        self._tol_frames = -1
        self._tol_known = None

    def _cand_tol(self) -> np.ndarray:
        """The allowance that vetoes a lost marker's candidate points: as `_tol`, with
        this body's own spread of each distance where it is wider than the set's
        (`learn_spread`). A tracked marker's distances are followed frame by frame
        (`_learn_distances`); a marker lost for a while comes back against distances
        learned before it was lost, and how far the body may have moved them since is
        its own spread. The set's allowance still ranks the candidates (and the lost
        markers competing for a point): the wider one only lets more in."""
        self._tol()
        return self._cand_tol_cache

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
        """(len(markers), len(P)): neighbour-distance error if marker took that point,
        against the set's spread (which ranks the candidates); `self._cand_veto` gets the
        same against the body's own spread where it is wider (`Labeller._cand_tol`),
        which alone decides whether a candidate is possible at all."""
        if self.compiled:
            mean, num, self._cand_chi2 = self.kern.candidate_error(
                markers, P, cur, self.nb, self.nb_mean, self._tol())
            self._cand_veto = mean
            if self._own_wider:
                self._cand_veto = self.kern.candidate_error(
                    markers, P, cur, self.nb, self.nb_mean, self._cand_tol())[0]
            return mean, num
        nbx = cur[self.nb[markers]]                                    # (L, K, 3)
        d = np.linalg.norm(P[None, :, None] - nbx[:, None], axis=3)    # (L, k, K)
        dev = np.abs(d - self.nb_mean[markers][:, None])
        e = dev / self._tol()[markers][:, None]
        ok = np.isfinite(e)
        num = ok.sum(2)
        mean = np.where(ok, np.minimum(e, 3.0), 0.0).sum(2) / np.maximum(num, 1)
        # the same as a sum of squares in units of the distances' SD (tolerance / 3), each
        # capped at 4 SD: a sum tells two candidates apart where a mean dilutes
        self._cand_chi2 = np.where(ok, np.minimum(9.0 * e * e, 16.0), 0.0).sum(2)
        self._cand_veto = mean
        if self._own_wider:
            e = dev / self._cand_tol()[markers][:, None]
            self._cand_veto = np.where(ok, np.minimum(e, 3.0), 0.0).sum(2) / np.maximum(num, 1)
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
