"""The local search's moves (daemon/labelling/assign.py's `polish`): which relabellings
it tries (a part of the body mirrored, a rigid module reordered, a group of markers
reordered) and what each changes the score by, many at a time.

Apart from assign.py, which builds the compatibility and runs the search: the search
tries a few hundred fixed moves a round, and scoring each one by itself in Python was
most of a start window's and a verification's time. `MoveTable` scores all of them in
a few batched gathers and hands the search only those that can still win.
"""

from __future__ import annotations

from itertools import permutations

import numpy as np

from daemon.labelling.body import BodyTerms
from daemon.labelling.markerset import MarkerSet
from daemon.labelling.modules import rigid_modules

# the batched estimate may differ from the exact one by rounding (the same float32 table
# summed in another order, about 1e-10 on scores of hundreds): a move is handed on unless
# it falls short of the best by more than this, and the search then scores it exactly
SLACK = 1e-6


def mirror_moves(ms: MarkerSet, twin: np.ndarray) -> list[np.ndarray]:
    """Marker permutations that turn one part of the body into its mirror image: each
    segment, and each segment with its descendants in the set's tree, together with its
    left/right twins, each marker taken for its twin."""
    segs = ms.segments
    children: dict[int, list[int]] = {k: [] for k in range(len(segs))}
    for k, sg in enumerate(segs):
        if sg.parent >= 0:
            children[sg.parent].append(k)

    def subtree(k: int) -> list[int]:
        out, todo = [], [k]
        while todo:
            s = todo.pop()
            out += list(segs[s].markers)
            todo += children[s]
        return out

    moves, seen = [], set()
    for k in range(len(segs)):
        for members in (list(segs[k].markers), subtree(k)):
            S = np.unique(np.concatenate([members, twin[members]]))
            if (twin[S] == S).all():
                continue
            perm = np.arange(ms.n)
            perm[S] = twin[S]
            key = perm.tobytes()
            if key not in seen:
                seen.add(key)
                moves.append(perm)
    return moves


def module_moves(terms: BodyTerms) -> list[tuple[np.ndarray, int]]:
    """Reorderings inside each rigid module of 4-5 markers (all its permutations), with
    the module's index in `terms`."""
    out = []
    for k, m in enumerate(terms.modules):
        if len(m) <= 5:
            for p in permutations(range(len(m))):
                if p != tuple(range(len(m))):
                    perm = np.arange(terms.ms.n)
                    perm[m] = m[list(p)]
                    out.append((perm, k))
    return out


def near_groups(ms: MarkerSet, size: int = 4, max_sd_m: float = 0.015) -> list[np.ndarray]:
    """Groups of `size` markers that move together (each with its nearest neighbours by
    the set's distance among those within `max_sd_m` spread of it) and that no rigid
    module holds whole: a head's four markers, 12-20 cm apart and sliding on the scalp
    by a centimetre, are no rigid module, and on a body built otherwise the set can
    prefer them turned by one place in one window and not in the next. A turn is a cycle
    of four labels no swap reaches one step at a time."""
    mods = [set(m.tolist()) for m in rigid_modules(ms)]
    out, seen = [], set()
    for i in range(ms.n):
        ok = np.nonzero(ms.sd_m[i] < max_sd_m)[0]
        ok = ok[ok != i]
        if len(ok) < size - 1:
            continue
        g = tuple(sorted([i, *ok[np.argsort(ms.mean_m[i, ok])[:size - 1]].tolist()]))
        if g in seen or any(set(g) <= m for m in mods):
            continue
        if (ms.sd_m[np.ix_(g, g)] >= max_sd_m).any():
            continue
        seen.add(g)
        out.append(np.array(g))
    return out


def group_moves(cp, G: np.ndarray, mt: np.ndarray, groups: list[np.ndarray]
                ) -> list[tuple[float, np.ndarray]]:
    """Every reordering of the labels inside each group of `groups` (near_groups) whose
    tracks are labelled, with the compatibility's change (exact, batched per group;
    G the gain at the labelling mt, marker -> track) where it is positive."""
    C4 = cp.C.reshape(cp.T, cp.n, cp.T, cp.n)
    out = []
    for g in groups:
        g = g[mt[g] >= 0]
        k = len(g)
        if k < 3:
            continue
        perms = np.array(list(permutations(range(k)))[1:])              # (P, k)
        a = mt[g]                                                        # tracks
        new = g[perms]                                                   # (P, k) markers
        lin = G[a[None], new].sum(1) - G[a, g].sum()
        aa = C4[a[None, :, None], new[:, :, None], a[None, None, :], new[:, None, :]]
        ra = C4[a[None, :, None], g[None, :, None], a[None, None, :], new[:, None, :]]
        rr = C4[a[:, None], g[:, None], a[None], g[None]].sum()
        d = lin + 0.5 * (rr + aa.sum((1, 2)) - 2.0 * ra.sum((1, 2)))
        for p in np.nonzero(d > 0)[0]:
            m2 = mt.copy()
            m2[new[p]] = a
            out.append((float(d[p]), m2))
    return out


def changed_bounds(terms: BodyTerms, first: np.ndarray, second: np.ndarray) -> np.ndarray:
    """`BodyTerms.gain_bound` of labellings that each change markers first[k] and
    second[k] (-1: none) from the last one scored, in one product."""
    changed = np.zeros((len(first), terms.ms.n))
    rows = np.arange(len(first))
    changed[rows, first] = 1.0
    two = second >= 0
    changed[rows[two], second[two]] = 1.0
    return terms.gain_bounds(changed)


class MoveTable:
    """A search's fixed moves (marker permutations, each with its module's index in the
    BodyTerms or -1), bucketed by how many markers each permutes, so that one round's
    moves are scored in one gather per bucket: the compatibility's exact change (as
    assign's `_sparse_delta` computes it one move at a time) plus the whole-body terms'
    bound (`BodyTerms.gain_bounds`)."""

    def __init__(self, moves: list[tuple[np.ndarray, int]], n: int) -> None:
        self.n = n
        self.module = np.array([k for _, k in moves], dtype=int)
        perms = np.stack([p for p, _ in moves]) if moves else np.zeros((0, n), int)
        moved = perms != np.arange(n)
        size = moved.sum(1)
        self.buckets = []       # (moves, the markers each permutes (B, L), whose track each takes)
        for L in np.unique(size[size > 0]):
            js = np.nonzero(size == L)[0]
            sup = np.nonzero(moved[js])[1].reshape(len(js), L)
            self.buckets.append((js, sup, np.take_along_axis(perms[js], sup, axis=1)))

    def candidates(self, C: np.ndarray, G: np.ndarray, mt: np.ndarray, terms: BodyTerms,
                   cur: float, best: float, every_order: bool) -> np.ndarray:
        """The moves (indices, in order) whose score (cur + change) plus the terms'
        bound may beat `best` (within SLACK): the only moves the search needs to score
        one by one. See `bounds`."""
        est = self.bounds(C, G, mt, terms, every_order)
        return np.nonzero(cur + est > best + 1e-6 - SLACK)[0]

    def bounds(self, C: np.ndarray, G: np.ndarray, mt: np.ndarray, terms: BodyTerms,
               every_order: bool) -> np.ndarray:
        """Per move: the compatibility's change from the labelling mt (marker -> track)
        plus the whole-body terms' bound (as last scored by `terms`); -inf for a move
        that changes nothing, and (unless `every_order`) for a reordering of a module
        whose shape fits, which the search leaves alone. C is the compatibility table
        (T n, T n), G its gain (T, n) at mt."""
        n = self.n
        Gf = G.reshape(-1)
        est = np.full(len(self.module), -np.inf)
        for js, sup, src in self.buckets:
            was, now = mt[sup], mt[src]                                      # (B, L)
            ch = now != was
            rem = ch & (was >= 0)
            add = ch & (now >= 0)
            kr = np.where(rem, was * n + sup, 0)
            ka = np.where(add, now * n + sup, 0)
            lin = np.where(add, Gf[ka], 0.0).sum(1) - np.where(rem, Gf[kr], 0.0).sum(1)
            k = np.concatenate([kr, ka], axis=1)
            u = np.concatenate([-rem.astype(float), add.astype(float)], axis=1)
            quad = 0.5 * np.einsum("bi,bij,bj->b", u, C[k[:, :, None], k[:, None, :]], u)
            changed = np.zeros((len(js), n))
            np.put_along_axis(changed, sup, ch, axis=1)
            est[js] = np.where(ch.any(1), lin + quad + terms.gain_bounds(changed), -np.inf)
        if not every_order:
            m = self.module
            own = m >= 0
            sizes = np.array([len(x) for x in terms.modules])
            fits = np.zeros(len(m), bool)
            fits[own] = terms.cost[m[own]] < sizes[m[own]]
            est[fits] = -np.inf
        return est
