"""The global assignment of tracks to a marker set's markers, from the set alone.

A labelling grown one marker at a time from a single frame by the set's distances goes
wrong on a body the set was not learned on (another size, markers stuck elsewhere): a
leg's labels shift by one marker, or left and right mix. Here tracks (a window's points
linked over time, daemon/labelling/start.py) are assigned all at once:

1. every pair of (track -> marker) assignments gets a compatibility: how well the two
   tracks' distance fits the two markers' distance in the set, scaled to this body and
   with an allowance for another subject (a fraction of the distance), and whether a
   pair the set says is rigid stays rigid over the tracks (two points on one segment
   keep their distance while the body moves, whatever its size);
2. the assignment maximising the summed compatibility (a quadratic assignment) is found
   by graduated assignment (softassign: Sinkhorn-balanced soft matches sharpened step by
   step) from several starts, each made discrete by linear assignments (Hungarian) on
   the compatibility's gradient until it no longer changes;
3. distances cannot tell a body from its mirror image, so each solution's left/right twin
   (markers named L.../R...) is tried too, and the set's handedness tetrahedra (signed
   volumes over the window) and the shapes of its rigid modules vote between them; the
   best whole-body score wins after a local search (swaps, mirror moves of a segment,
   reorderings inside a module).
"""

from __future__ import annotations

import numpy as np

from calibkit.core.assignment import linear_sum_assignment
from daemon.labelling.body import HAND_WEIGHT, MODULE_WEIGHT, BodyTerms
from daemon.labelling.markerset import MarkerSet
from daemon.labelling.modules import rigid_modules
from daemon.labelling.moves import (  # noqa: F401  (near_groups: the tests' name for it)
    SLACK,
    MoveTable,
    changed_bounds,
    group_moves,
    mirror_moves,
    module_moves,
    near_groups,
)

SUBJECT_REL = 0.12      # another body: a distance may differ by this fraction (1 SD)
PLACEMENT_M = 0.012     # ... and by this much from markers stuck elsewhere (1 SD)
RIGID_SD_M = 0.008      # pairs whose set spread is below this keep their distance
RIGID_REL = 0.4        # ... and a rigid pair that stays rigid may differ by this fraction
RIGID_REWARD = 0.7     # ... scoring at least this (a pair fitting the set's distance: 1)
RIGID_BONUS = 0.5      # ... and this more: the window's rigidity is evidence of its own


def pair_stats(X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean distance and its SD (T, T) between tracks (T, W, 3) over the frames both are
    seen in (NaN for pairs never seen together)."""
    diff = X[:, None] - X[None]                                   # (T, T, W, 3)
    d = np.sqrt(np.einsum("abwi,abwi->abw", diff, diff))
    ok = np.isfinite(d)
    c = ok.sum(2)
    d0 = np.where(ok, d, 0.0)
    mean = d0.sum(2) / np.maximum(c, 1)
    var = (d0 * d0).sum(2) / np.maximum(c, 1) - mean ** 2
    mean[c < 3] = np.nan
    return mean, np.sqrt(np.maximum(var, 0.0))



def mirror_map(labels: list[str]) -> np.ndarray:
    """Each marker's left/right twin by name (L... <-> R..., Left <-> Right, ..._L <->
    ..._R); a marker without one is its own twin (the mid-line)."""
    idx = {n: i for i, n in enumerate(labels)}
    out = np.arange(len(labels))
    pairs = (("L", "R"), ("Left", "Right"), ("left", "right"))
    for i, name in enumerate(labels):
        for a, b in pairs + tuple((y, x) for x, y in pairs):
            for twin in ((b + name[len(a):]) if name.startswith(a) else None,
                         (name[:-len(a)] + b) if name.endswith("_" + a) else None):
                if twin is not None and twin in idx and twin != name:
                    out[i] = idx[twin]
    ok = out[out] == np.arange(len(labels))       # a twin must be mutual
    return np.where(ok, out, np.arange(len(labels)))


class Compat:
    """Pairwise compatibilities C[a, i, b, j] of track a as marker i together with track
    b as marker j, for one window and one body scale."""

    def __init__(self, ms: MarkerSet, D: np.ndarray, S: np.ndarray, scale: float,
                 noise_m: float = 0.003) -> None:
        T, n = len(D), ms.n
        M = ms.mean_m * scale
        sub = np.maximum(ms.subject_sd_m * scale, SUBJECT_REL * M)
        tol = np.sqrt(ms.sd_m ** 2 + sub ** 2 + PLACEMENT_M ** 2 + 2 * noise_m ** 2)
        known = np.isfinite(D)
        f4 = np.float32
        Dz = np.where(known, D, 0.0).astype(f4)
        # C = exp(-e^2 / 2), e = (D[a, b] - M[i, j]) / tol[i, j], in place and in single
        # precision (5x faster; the sums over it are taken in double): the (T, n, T, n)
        # table is the cost of the start (and of every verification)
        C = Dz[:, None, :, None] - M.astype(f4)[None, :, None, :]
        C /= tol.astype(f4)[None, :, None, :]
        C *= C
        C *= f4(-0.5)
        np.exp(C, out=C)
        # a pair the set says is rigid must stay rigid in the window ...
        allow = 3.0 * ms.sd_m + 2.0 * noise_m + 0.004
        ri, rj = np.nonzero(ms.sd_m < RIGID_SD_M)
        Sz = np.where(known, S, 0.0)
        sub = C[:, ri, :, rj]                                           # (K, T, T)
        bad = Sz[None] > allow[ri, rj][:, None, None]
        sub[bad] *= f4(0.05)
        # ... and one that does keeps it, wherever its markers sit on the segment: a
        # rigid pair within a loose allowance scores at least RIGID_REWARD
        loose = (RIGID_REL * M + 0.02)[ri, rj][:, None, None].astype(f4)
        e2 = (Dz[None] - M[ri, rj][:, None, None].astype(f4)) / loose
        near = np.exp(f4(-0.5) * e2 * e2)
        C[:, ri, :, rj] = np.where(~bad, np.maximum(sub, f4(RIGID_REWARD) * near)
                                   + f4(RIGID_BONUS) * near, sub)
        C.transpose(0, 2, 1, 3)[~known] = 0.0        # pairs of tracks never seen together
        ia, ib = np.arange(T), np.arange(n)
        C[ia, :, ia, :] = 0.0
        C[:, ib, :, ib] = 0.0
        self.C = C.reshape(T * n, T * n)
        self.T, self.n = T, n

    def gain(self, P: np.ndarray) -> np.ndarray:
        """The gradient (T, n) of the summed compatibility at (soft) assignment P."""
        k = _matched(P)
        if k is not None:          # a 0/1 assignment: the sum of its rows of C (C = C^T)
            return self.C[k].sum(0, dtype=np.float64).reshape(self.T, self.n)
        return self.soft_gain(P)

    def soft_gain(self, P: np.ndarray) -> np.ndarray:
        """`gain` at a soft assignment, in single precision (softassign's soft matches
        are only steered by it; the discrete assignments are judged in double)."""
        G = self.C @ P.reshape(-1).astype(np.float32)
        return G.astype(np.float64).reshape(self.T, self.n)

    def score(self, P: np.ndarray) -> float:
        k = _matched(P)
        if k is not None:
            return 0.5 * float(self.C[np.ix_(k, k)].sum(dtype=np.float64))
        G = self.soft_gain(P)
        return 0.5 * float(P.reshape(-1) @ G.reshape(-1))


def _matched(P: np.ndarray) -> np.ndarray | None:
    """The flat indices of a 0/1 assignment's matches, or None for a soft one (the
    product with the whole table is the start's cost; a 0/1 one needs T of its rows)."""
    flat = P.reshape(-1)
    k = np.flatnonzero(flat)
    if len(k) > P.shape[0] or not (flat[k] == 1.0).all():
        return None
    return k


def _discrete(G: np.ndarray) -> np.ndarray:
    """The 0/1 assignment (T, n) maximising sum G over matched pairs, each track and
    marker used at most once, no match with a non-positive gain."""
    r, c = linear_sum_assignment(-G)
    P = np.zeros_like(G)
    ok = G[r, c] > 0
    P[r[ok], c[ok]] = 1.0
    return P


def refine(cp: Compat, P: np.ndarray, iters: int = 20) -> np.ndarray:
    """Linear assignments on the gradient until the assignment stops changing (each
    step can only raise the score: a local optimum of the quadratic assignment)."""
    best = cp.score(P)
    for _ in range(iters):
        Q = _discrete(cp.gain(P))
        s = cp.score(Q)
        if s <= best + 1e-9:
            break
        P, best = Q, s
    return P


def softassign(cps: list[Compat], P0: np.ndarray, betas=(0.5, 1, 2, 4, 8, 16, 32),
               inner: int = 3) -> np.ndarray:
    """Graduated assignment: soft matches from the gradient, Sinkhorn-balanced (with a
    slack row and column for unmatched tracks and markers), sharpened step by step.
    Runs for each table of `cps` its starts P0[k] (R, T, n) (the start's restarts at
    its scales), all of a table's starts together: one product with the table a step.

    A table is run to the end before the next: one (11 MB in single precision for 41
    markers) stays in the cache over its 21 products, where three taken in turn are
    read from memory each time (96 -> 67 ms on 85_02's start, the same soft matches)."""
    return np.stack([_softassign_one(cp, P0[k], betas, inner) for k, cp in enumerate(cps)])


def _softassign_one(cp: Compat, P0: np.ndarray, betas, inner: int) -> np.ndarray:
    """`softassign` on one table. The balancing keeps the table fixed and scales its
    rows (u) and columns (v), the slack row's and column's scale held at 1 (they are
    never normalised): two batched products a step instead of four passes over it."""
    R, T, n = P0.shape
    P = P0
    Q = np.ones((R, T + 1, n + 1))
    Qt = np.swapaxes(Q, 1, 2)
    for beta in betas:
        slack = np.exp(-beta * 4.0 * 0.7)
        for _ in range(inner):
            G = (cp.C @ P.reshape(R, -1).T.astype(np.float32)).T.astype(np.float64)
            G /= np.maximum(G.max(1, keepdims=True), 1e-12)
            Q[:, :T, :n] = np.exp(beta * 4.0 * (G.reshape(R, T, n) - 1.0))
            Q[:, :T, n] = slack
            Q[:, T, :n] = slack
            Q[:, T, n] = 1.0
            u = np.ones((R, T + 1, 1))
            v = np.ones((R, n + 1, 1))
            for _ in range(30):
                u[:, :T] = 1.0 / (Q[:, :T] @ v)
                v[:, :n] = 1.0 / (Qt[:, :n] @ u)
            P = u[:, :T] * Q[:, :T, :n] * v[:, :n, 0][:, None, :]
    return P


def _sparse_delta(cp: Compat, G: np.ndarray, rem: tuple, add: tuple) -> float:
    """The compatibility's change when the (track, marker) matches `rem` (two index
    arrays) are dropped and `add` taken, G the gain at the current assignment."""
    ka = rem[0] * cp.n + rem[1]
    kb = add[0] * cp.n + add[1]
    k = np.concatenate([ka, kb])
    u = np.concatenate([-np.ones(len(ka)), np.ones(len(kb))])
    return float(u @ G.reshape(-1)[k] + 0.5 * u @ cp.C[np.ix_(k, k)] @ u)


def to_marker_track(P: np.ndarray) -> np.ndarray:
    mt = np.full(P.shape[1], -1)
    r, c = np.nonzero(P)
    mt[c] = r
    return mt


def chain_groups(ms: MarkerSet, max_sd_m: float = RIGID_SD_M) -> list[np.ndarray]:
    """Each marker with its two steadiest neighbours by the set (spread under
    `max_sd_m`: the joint's markers of a limb, thigh-knee-shank), as groups for
    `group_moves`, where no rigid module holds them whole. On a body built otherwise
    than the set's the three labels can come out turned by one place along the chain
    (a cycle of three no swap reaches one step at a time); their markers are 20-40 cm
    apart, so `near_groups` does not hold them."""
    mods = [set(m.tolist()) for m in rigid_modules(ms)]
    out, seen = [], set()
    for i in range(ms.n):
        sd = ms.sd_m[i].copy()
        sd[i] = np.inf
        two = np.argsort(sd)[:2]
        if not (sd[two] < max_sd_m).all():
            continue
        g = tuple(sorted([i, *two.tolist()]))
        if g in seen or any(set(g) <= m for m in mods):
            continue
        seen.add(g)
        out.append(np.array(g))
    return out


def polish(cp: Compat, P: np.ndarray, terms: BodyTerms, moves: list[tuple],
           rounds: int = 30, near: float = 2.0, max_swaps: int = 60, allowed=None,
           every_order: bool = False, groups: list[np.ndarray] = ()
           ) -> tuple[np.ndarray, float]:
    """Local search on the whole-body score (compatibility, handedness and module
    shapes): swaps of two markers' tracks that the compatibility leaves within `near` of
    the best, mirror moves of a part of the body and reorderings inside a rigid module
    (of a module whose shape fits as it is, only with `every_order`: a tracker can turn
    a nearly symmetric foot half round, heel for toe and ankle for 5th metatarsal, and
    its shape still fits); the best improving move at a time. `allowed(mt)` (marker ->
    track), if given, says which labellings the search may move to."""
    ok = allowed or (lambda mt: True)
    T, n = cp.T, cp.n
    C4 = cp.C.reshape(T, n, T, n)
    base = cp.score(P)
    mt = to_marker_track(P)
    cur = base + terms(mt)
    table = MoveTable(moves, n)
    for _ in range(rounds):
        G = cp.gain(P)
        a, i = np.nonzero(P)
        if len(a) < 2:
            break
        # each kind of move gives its candidates (the labelling, the compatibility's
        # score, whole) in the order they are tried; `_best_move` scores them
        cands = []
        d = (G[a[:, None], i[None]] + G[a[None], i[:, None]] - G[a, i][:, None]
             - G[a, i][None] + C4[a[:, None], i[None], a[None], i[:, None]]
             + C4[a[:, None], i[:, None], a[None], i[None]])
        xs, ys = np.nonzero(np.triu(d > -near, 1))
        top = np.argsort(-d[xs, ys])[:max_swaps]
        bound = changed_bounds(terms, i[xs[top]], i[ys[top]])   # (gain_bound, batched)
        for x, y, b in zip(xs[top], ys[top], bound, strict=True):
            if cur + d[x, y] + b > cur + 1e-6 - SLACK:
                m2 = mt.copy()
                m2[i[x]], m2[i[y]] = mt[i[y]], mt[i[x]]
                cands.append((m2, cur + d[x, y]))
        # a track taking a marker no track has (its own marker left free)
        free = np.nonzero(mt < 0)[0]
        if len(free):
            d1 = G[a[:, None], free[None]] - G[a, i][:, None]
            xs, ks = np.nonzero(np.isfinite(d1))
            bound = changed_bounds(terms, i[xs], free[ks])
            for x, k, b in zip(xs, ks, bound, strict=True):
                if cur + d1[x, k] + b > cur + 1e-6 - SLACK:
                    m2 = mt.copy()
                    m2[i[x]], m2[free[k]] = -1, a[x]
                    cands.append((m2, cur + d1[x, k]))
        # a track no marker has taking a free marker, or taking a marker whose track
        # moves to a free one (a tracker that gave a marker's label to its neighbour and
        # left the marker's own point unlabelled)
        un = np.setdiff1d(np.arange(T), a)
        if len(un) and len(free):
            d2 = (G[un][:, i][:, :, None] + G[a][:, free][None] - G[a, i][None, :, None]
                  + C4[un[:, None, None], i[None, :, None], a[None, :, None],
                       free[None, None, :]])                                   # (U, A, F)
            swaps = [(G[un[u], free[f]], un[u], -1, free[f])
                     for u, f in zip(*np.nonzero(G[un][:, free] > -near), strict=True)]
            us, xs, fs = np.nonzero(d2 > -near)
            top = np.argsort(-d2[us, xs, fs])[:max_swaps]
            swaps += [(d2[u, x, f], un[u], x, free[f])
                      for u, x, f in zip(us[top], xs[top], fs[top], strict=True)]
            bound = changed_bounds(terms, np.array([c[3] for c in swaps], int),
                                   np.array([i[c[2]] if c[2] >= 0 else -1 for c in swaps], int))
            for (dv, u, x, f), b in zip(swaps, bound, strict=True):
                if cur + dv + b > cur + 1e-6 - SLACK:
                    m2 = mt.copy()
                    if x < 0:
                        m2[f] = u
                    else:
                        m2[i[x]], m2[f] = u, a[x]
                    cands.append((m2, cur + dv))
        cands += [(m2, cur + dv) for dv, m2 in group_moves(cp, G, mt, groups)]
        arg, best = _best_move(cands, terms, ok, cur, None)
        cands = []
        for j in table.candidates(cp.C, G, mt, terms, cur, best, every_order):
            perm, k = moves[j]      # (only those that can still win; each scored exactly)
            if k >= 0 and terms.cost[k] < len(terms.modules[k]) and not every_order:
                continue                   # the module fits as it is: leave its order
            m2 = mt[perm]
            ch = np.nonzero(m2 != mt)[0]
            if not len(ch):
                continue
            o = ch[mt[ch] >= 0]
            nw = ch[m2[ch] >= 0]
            cands.append((m2, cur + _sparse_delta(cp, G, (mt[o], o), (m2[nw], nw))))
        arg, best = _best_move(cands, terms, ok, best, arg)
        if arg is None:
            break
        Q = np.zeros_like(P)
        got = arg >= 0
        Q[arg[got], np.nonzero(got)[0]] = 1.0
        R = refine(cp, Q)                 # the compatibility alone may undo the move:
        mr = to_marker_track(R)
        r = cp.score(R) + terms(mr) if ok(mr) else -np.inf
        P = R if r > best else Q          # keep its refinement only if the whole gains
        mt = to_marker_track(P)
        base = cp.score(P)
        cur = base + terms(mt)
    return P, cur


def _best_move(cands: list[tuple[np.ndarray, float]], terms: BodyTerms, allowed,
               best: float, arg: np.ndarray | None) -> tuple[np.ndarray | None, float]:
    """The first candidate labelling, in order, of the highest whole score above `best`
    (each given with its compatibility score), else `arg`: the handedness part of every
    candidate in one batch, a candidate's module shapes scored only where it can still
    win."""
    if not cands:
        return arg, best
    hand, mod_bound = terms.hand_changes(np.stack([m2 for m2, _ in cands]))
    for (m2, s0), dv, mb in zip(cands, hand, mod_bound, strict=True):
        if s0 + HAND_WEIGHT * dv + mb <= best + 1e-6 or not allowed(m2):
            continue
        s = s0 + (HAND_WEIGHT * dv - MODULE_WEIGHT * terms.module_change(m2))
        if s > best + 1e-6:
            best, arg = s, m2
    return arg, best


def body_scale(D: np.ndarray, ms: MarkerSet) -> float:
    """This body's size against the set's: the RMS distance between the window's tracks
    over the RMS distance between the set's markers (posture moves it by a few per cent;
    the compatibility allows for more)."""
    iu = np.triu_indices(len(D), 1)
    d = D[iu]
    d = d[np.isfinite(d)]
    m = ms.mean_m[np.triu_indices(ms.n, 1)]
    if not len(d):
        return 1.0
    return float(np.clip(np.sqrt(np.mean(d ** 2) / np.mean(m ** 2)), 0.6, 1.6))


def assign(X: np.ndarray, ms: MarkerSet, restarts: int = 6, seed: int = 0,
           scales=(0.92, 1.0, 1.08), noise_m: float = 0.003, keep: int = 2
           ) -> tuple[np.ndarray, float]:
    """The marker of each track (T,) (-1: none) for tracks X (T, W, 3), and its score.
    Solutions are sought with the set scaled to this body's size and a little either
    side of it, and all are scored (and polished) at this body's size. (Tracks whose
    names fit no marker of the set left out: daemon/labelling/unfit.py's assign_pruned.)"""
    lab, score, _judge, _terms = assign_tables(X, ms, restarts, seed, scales, noise_m, keep)
    return lab, score


def assign_tables(X: np.ndarray, ms: MarkerSet, restarts: int = 6, seed: int = 0,
                  scales=(0.92, 1.0, 1.08), noise_m: float = 0.003, keep: int = 2):
    """`assign`'s labels and score, with the compatibility table and body terms it
    scored them by (for a caller that goes on scoring relabellings the same way)."""
    T, n = X.shape[0], ms.n
    D, S = pair_stats(X)
    size = body_scale(D, ms)
    twin = mirror_map(ms.labels)
    terms = BodyTerms(X, ms, noise_m=noise_m)
    moves = [(p, -1) for p in mirror_moves(ms, twin)] + module_moves(terms)
    rng = np.random.default_rng(seed)
    judge = Compat(ms, D, S, size, noise_m)
    found: list[tuple[float, int, np.ndarray]] = []
    seen: set[bytes] = set()
    cps = [judge if scale == 1.0 else Compat(ms, D, S, size * scale, noise_m)
           for scale in scales]
    starts = np.stack([np.concatenate([np.full((1, T, n), 1.0 / n),
                                       rng.random((restarts - 1, T, n))]) for _ in cps])
    for cp, soft in zip(cps, softassign(cps, starts), strict=True):
        for S0 in soft:
            P = refine(cp, _discrete(S0))
            for Q in (P, refine(cp, P[:, twin])):
                Q = refine(judge, Q)
                key = Q.tobytes()
                if key in seen:
                    continue
                seen.add(key)
                total = judge.score(Q) + terms(to_marker_track(Q))
                found.append((total, len(found), Q))
    found.sort(key=lambda f: -f[0])
    best = None
    for _, _, Q in found[:keep]:
        Q, s = polish(judge, Q, terms, moves)
        if best is None or s > best[0]:
            best = (s, Q)
    assert best is not None
    lab = np.full(T, -1)
    r, c = np.nonzero(best[1])
    lab[r] = c
    return lab, best[0], judge, terms
