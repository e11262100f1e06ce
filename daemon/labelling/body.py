"""The whole-body terms of the start's score beyond the pairwise distances: the set's
handedness tetrahedra and the shapes of its rigid modules.

Distances cannot tell a body from its mirror image, nor a foot's markers turned around
their tetrahedron; the signs of the set's handedness quadruples and a proper (no
reflection) fit of each rigid module's shape can. The global assignment
(daemon/labelling/assign.py) and the verification (verify.py) add these terms
to the pairwise compatibility, and score a labelling that differs in a few markers from
the last one by what changed only.
"""

from __future__ import annotations

import numpy as np

from daemon.labelling.markerset import MarkerSet
from daemon.labelling.modules import module_template, rigid_modules, template_sigma

MODULE_WEIGHT = 0.3    # score per marker of a rigid module per unit chi-square of its shape
HAND_WEIGHT = 1.0       # score per handedness vote, in units of one well-fitting pair


class BodyTerms:
    """The terms of the whole-body score beyond the pairwise compatibility, for one
    window: the set's handedness tetrahedra (signed volumes' signs over the window
    against the set's) and the shapes of its rigid modules (a proper, scaled Procrustes
    fit of the set's shape of each module of 4+ markers, which tells a module from its
    mirror image and its reorderings)."""

    def __init__(self, X: np.ndarray, ms: MarkerSet, frames: int = 6,
                 noise_m: float = 0.003) -> None:
        self.ms = ms
        W = X.shape[1]
        self.X = X[:, np.linspace(0, W - 1, min(W, frames)).astype(int)]     # (T, f, 3)
        self.quads = np.concatenate([ms.chiral, ms.pair_quads]).astype(int).reshape(-1, 4)
        self.signs = np.concatenate([ms.chiral_sign, ms.pair_sign])
        self.modules = [m for m in rigid_modules(ms) if len(m) >= 4]
        self.shapes = [module_template(ms, m) for m in self.modules]
        self.sigma = np.array([template_sigma(ms, m, noise_m) for m in self.modules])

        # which quads and modules each marker is in ((n, quads), (n, modules)), so that the
        # terms a change touches are one `any` over the changed markers' rows
        self.in_quad = (self.quads[None] == np.arange(ms.n)[:, None, None]).any(2)
        self.in_module = np.zeros((ms.n, len(self.modules)), bool)
        for k, m in enumerate(self.modules):
            self.in_module[m, k] = True
        self._last_affected: tuple[bytes, tuple] = (b"", ())
        self.mt = None
        self._memo: dict[tuple, float] = {}
        self._incidence = (self.in_quad.astype(float), self.in_module.astype(float))

    def _votes(self, mt: np.ndarray, q: np.ndarray) -> np.ndarray:
        """Each quad's vote (+1 agrees with the set, -1 not, 0 unknown) among quads q."""
        return self._votes_of(mt[self.quads[q]], q)

    def _votes_of(self, tracks: np.ndarray, q: np.ndarray) -> np.ndarray:
        """The votes of quads q whose markers have the tracks (len(q), 4), -1: none."""
        out = np.zeros(len(q))
        if not len(q):
            return out
        ok = (tracks >= 0).all(1)
        if not ok.any():
            return out
        x = self.X[tracks[ok]]                                      # (q, 4, f, 3)
        a, b, c = (x[:, k] - x[:, 0] for k in (1, 2, 3))
        v = ((a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1]) * c[..., 0]   # (a x b) . c,
             + (a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2]) * c[..., 1]  # written out:
             + (a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]) * c[..., 2])  # np.cross is slow
        s = np.sign(np.sign(np.where(np.isfinite(v), v, 0.0)).sum(1))     # majority
        out[ok] = s * self.signs[q[ok]]
        return out

    def _module_cost(self, mt: np.ndarray, k: int) -> float:
        """Markers x chi-square per marker (capped at 16) of module k's shape, fitted to
        its labelled markers (3 or more); a member left unlabelled costs 1 (as much as
        one that fits), so that leaving a marker out does not pay."""
        key = (k, *mt[self.modules[k]].tolist())
        if key not in self._memo:
            self._memo[key] = self._module_cost_of(mt, k)
        return self._memo[key]

    def _module_cost_of(self, mt: np.ndarray, k: int) -> float:
        m = self.modules[k]
        have = mt[m] >= 0
        if have.sum() < 3:
            return float(len(m))
        x = np.swapaxes(self.X[mt[m[have]]], 0, 1)                  # (f, h, 3)
        ok = np.isfinite(x).all((1, 2))
        if not ok.any():
            return float(len(m))
        r2 = _scaled_proper_residual(self.shapes[k][have], x[ok])
        chi2 = min(float(np.median(r2)) / self.sigma[k] ** 2, 16.0)
        return have.sum() * chi2 + (~have).sum()

    def __call__(self, mt: np.ndarray) -> float:
        """The terms' value for the labelling mt (marker -> track); remembered, so that
        `hand_changes` and `module_change` can score labellings that differ from it in a
        few markers."""
        self.mt = mt.copy()
        self._last_affected = (b"", ())
        self.vote = self._votes(mt, np.arange(len(self.quads)))
        self.cost = np.array([self._module_cost(mt, k) for k in range(len(self.modules))])
        return HAND_WEIGHT * self.vote.sum() - MODULE_WEIGHT * self.cost.sum()

    def _affected(self, m2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The quads and modules (ascending) whose markers m2 changes from the last
        labelling scored; the last answer is kept (a bound and a change ask in turn)."""
        key = m2.tobytes()
        if key != self._last_affected[0]:
            ch = m2 != self.mt
            self._last_affected = (key, (np.nonzero(self.in_quad[ch].any(0))[0],
                                         np.nonzero(self.in_module[ch].any(0))[0]))
        return self._last_affected[1]

    def gain_bound(self, m2: np.ndarray) -> float:
        """At most how much the terms can rise from the last labelling to m2."""
        q, ks = self._affected(m2)
        return HAND_WEIGHT * float((1.0 - self.vote[q]).sum()) + \
            MODULE_WEIGHT * float(self.cost[ks].sum())

    def gain_bounds(self, changed: np.ndarray) -> np.ndarray:
        """`gain_bound` of many labellings at once, each given by the markers it changes
        from the last one scored ((m, n), 1 where changed): the local search's fixed
        moves are bounded in one product instead of one call each."""
        q, k = self._incidence
        return (HAND_WEIGHT * ((changed @ q) > 0) @ (1.0 - self.vote)
                + MODULE_WEIGHT * ((changed @ k) > 0) @ self.cost)

    def module_change(self, m2: np.ndarray) -> float:
        """The modules' cost change from the last labelling scored to m2."""
        _, ks = self._affected(m2)
        return sum(self._module_cost(m2, k) - self.cost[k] for k in ks)

    def hand_changes(self, M2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """For many labellings (K, n) at once: the handedness votes' change from the
        last labelling scored, exactly (every changed quad of every labelling in one
        gather), and the bound of the modules' part (`gain_bound`'s). A local search
        then scores a candidate's module shapes, the costly part, only where the two
        together can still beat its best."""
        K = len(M2)
        if not K:
            return np.zeros(0), np.zeros(0)
        q_inc, k_inc = self._incidence
        ch = (M2 != self.mt).astype(float)
        k, q = np.nonzero(ch @ q_inc > 0)
        d = self._votes_of(M2[k[:, None], self.quads[q]], q) - self.vote[q]
        dv = np.bincount(k, weights=d, minlength=K)
        return dv, MODULE_WEIGHT * (((ch @ k_inc) > 0) @ self.cost)


def _scaled_proper_residual(shape: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Mean squared residual per frame (f,) of the best proper rotation, translation and
    scale (within 0.8-1.25) of `shape` (k, 3) onto each frame's points x (f, k, 3)."""
    S0 = shape - shape.mean(0)
    X0 = x - x.mean(1, keepdims=True)
    H = np.einsum("ki,fkj->fij", S0, X0)
    U, sv, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(np.einsum("fji,fkj->fik", Vt, U)))
    d = np.where(d == 0, 1.0, d)
    sv = sv.copy()
    sv[:, 2] *= d
    Vt = Vt.copy()
    Vt[:, 2] *= d[:, None]
    R = np.einsum("fji,fkj->fik", Vt, U)
    scale = np.clip(sv.sum(1) / (S0 ** 2).sum(), 0.8, 1.25)
    fit = scale[:, None, None] * np.einsum("fij,kj->fki", R, S0)
    return ((fit - X0) ** 2).sum(2).mean(1)
