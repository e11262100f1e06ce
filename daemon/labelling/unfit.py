"""Tracks the global assignment named but whose rigid neighbours do not vouch for the name.

A marker the set lacks (another lab's addition, stuck on a segment a few centimetres from
one of the set's markers) is a steady track like any other, and the assignment
(daemon/labelling/assign.py) names it anyway: every pair of tracks it labels adds to its
score, a wrong name only adds less. On one body wearing three such markers the start's
assignment named one C7, C7's own track RBHD, and so on round the head and both feet
(78.9 % right). What gives such a name away is the pairs the set calls rigid: a marker of
the set sits beside its rigid neighbours as the set says (a mean compatibility of 0.14-1
over them on bodies built otherwise), a name pushed onto the wrong track does not (0-0.07).
"""

from __future__ import annotations

import numpy as np

from daemon.labelling.assign import (
    RIGID_SD_M,
    Compat,
    assign,
    assign_tables,
    pair_stats,
    to_marker_track,
)
from daemon.labelling.markerset import MarkerSet

UNFIT = 0.1            # a name its rigid neighbours vouch for less than this is unfit
PRUNE_ROUNDS = 3       # rounds of leaving unfit tracks out (each one more assignment)
LEFT_OUT_COST = 5.0    # a track left out may cost the whole score at most this (5 pairs)


def unfit_tracks(cp: Compat, lab: np.ndarray, ms: MarkerSet, D: np.ndarray) -> np.ndarray:
    """Tracks whose marker the pairs the set calls rigid do not vouch for: over the
    labelled tracks whose markers keep a steady distance to its marker (RIGID_SD_M), a
    mean compatibility under UNFIT (a marker of the set sits as the set says beside its
    rigid neighbours, 0.14-1 on bodies built otherwise; a marker the set lacks, named by
    the search, 0-0.07). D: the tracks' mean distances (pairs never seen together: NaN)."""
    got = np.nonzero(lab >= 0)[0]
    if len(got) < 3:
        return np.zeros(0, int)
    C4 = cp.C.reshape(cp.T, cp.n, cp.T, cp.n)
    pair = C4[got[:, None], lab[got][:, None], got[None], lab[got][None]]    # (g, g)
    rig = (ms.sd_m[np.ix_(lab[got], lab[got])] < RIGID_SD_M) & np.isfinite(D[np.ix_(got, got)])
    np.fill_diagonal(rig, False)
    count = rig.sum(1)
    support = np.where(rig, pair, 0.0).sum(1) / np.maximum(count, 1)
    return got[(count >= 1) & (support < UNFIT)]


def assign_pruned(X: np.ndarray, ms: MarkerSet, restarts: int = 6, seed: int = 0,
                  scales=(0.92, 1.0, 1.08), noise_m: float = 0.003, keep: int = 2,
                  left: list | None = None) -> tuple[np.ndarray, float]:
    """`assign`, then the tracks whose names their rigid neighbours do not vouch for
    left out (`without_unfit`); their indices added to `left` if given."""
    lab, score, judge, terms = assign_tables(X, ms, restarts, seed, scales, noise_m, keep)
    lab, score, out = without_unfit(X, ms, lab, score, judge, terms,
                                    dict(restarts=restarts, seed=seed, scales=scales,
                                         noise_m=noise_m, keep=keep))
    if left is not None:
        left.extend(out.tolist())
    return lab, score


def without_unfit(X: np.ndarray, ms: MarkerSet, lab: np.ndarray, score: float,
                  judge: Compat, terms, options: dict) -> tuple[np.ndarray, float, np.ndarray]:
    """The labels `lab` (score `score`, from `assign` with its table `judge` and body
    terms `terms`) with the tracks whose names are unfit (`unfit_tracks`) left out and
    the rest assigned again (`options`: assign's), round by round (a freed name may go
    to another track that does not fit it either); a round's labels are taken when they
    explain the rest at least as well as the labels before it did without those tracks,
    and the rounds' labels when the whole score lost is under LEFT_OUT_COST a track
    left out (a marker the set lacks adds little under a name that does not fit it; on
    a start the search scrambled, four real tracks left out cost 42 units, and the take
    11 points).
    Returns the labels, their score and the tracks left out."""
    def total(one):
        P = np.zeros((len(X), ms.n))
        g = np.nonzero(one >= 0)[0]
        P[g, one[g]] = 1.0
        return judge.score(P) + terms(to_marker_track(P))

    D = pair_stats(X)[0]
    first, lab0 = score, lab.copy()
    left = np.zeros(len(X), bool)              # tracks left out so far
    for _ in range(PRUNE_ROUNDS):              # (another may take the freed name)
        out = unfit_tracks(judge, lab, ms, D)
        if not len(out):
            break
        left[out] = True
        rest = np.nonzero(~left)[0]
        sub, _ = assign(X[rest], ms, **options)
        new = np.full(len(X), -1)
        new[rest] = sub
        old = np.where(left, -1, lab)
        s_new = total(new)
        if s_new < total(old) - 1e-6:
            left[out] = False
            break
        lab, score = new, s_new
    if score < first - LEFT_OUT_COST * left.sum():       # real tracks left out: undone
        return lab0, first, np.zeros(0, int)
    # a track left out whose best-vouched name is free (a marker of the set that had
    # taken another's name) takes it; a marker the set lacks rides a few cm from one of
    # the set's and is vouched for best as that one, which its own track holds
    changed = False
    for t in np.nonzero(left)[0]:
        sup = rigid_support(judge, lab, ms, D, t)
        best = int(np.argmax(sup))
        if sup[best] >= UNFIT and not (lab == best).any():
            lab[t], left[t], changed = best, False, True
    return lab, total(lab) if changed else score, np.nonzero(left)[0]


def rigid_support(cp: Compat, lab: np.ndarray, ms: MarkerSet, D: np.ndarray, t: int
                  ) -> np.ndarray:
    """How well the other tracks' labels `lab` vouch for track t as each marker (n,):
    its mean compatibility with the labelled tracks whose markers the set keeps at a
    steady distance from that marker (-1 where there are none)."""
    got = np.nonzero((lab >= 0) & (np.arange(len(lab)) != t))[0]
    C4 = cp.C.reshape(cp.T, cp.n, cp.T, cp.n)
    pair = C4[t][:, got, lab[got]]                                        # (n, g)
    rig = (ms.sd_m[:, lab[got]] < RIGID_SD_M) & np.isfinite(D[t, got])[None]
    rig &= lab[got][None] != np.arange(ms.n)[:, None]
    count = rig.sum(1)
    return np.where(count > 0, np.where(rig, pair, 0.0).sum(1) / np.maximum(count, 1), -1.0)
