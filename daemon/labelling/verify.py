"""Verifying a take's labels window by window and relabelling where they went wrong.

Tracking carries a wrong labelling on as faithfully as a right one: a leg's labels
shifted by one marker, a side mirrored at the pelvis, two markers swapped after a long
occlusion all keep their distances from frame to frame, and the take's own distances,
learned as it goes, follow them. Only the marker set still says they are wrong. So each
window of frames is compared with the set (daemon/labelling/markerset_fit.py: a marker
whose distances to its steadiest neighbours are far outside the allowance for another
subject, a rigid segment that bends; and a handedness tetrahedron mirrored in most of
the window's frames); where one is, the window's labelled trajectories
are labelled again by the same global assignment that starts a take from the set alone
(daemon/labelling/assign.py), and the new labels are taken when they score clearly
better than the labels tracking gave. Every window first gets the assignment's local
search from its current labels, which is cheap and finds a side mirrored at the pelvis
(which no distance and, on the CMU set, no handedness tetrahedron shows by itself).
Points tracking left unlabelled are linked into tracks of their own and may take markers
no track holds: a tracker that gave a marker's label to its neighbour leaves the
marker's own point unlabelled, and only with it is the right labelling a reordering. A
relabelling found in one window is carried back to the windows before it that cannot
tell by themselves (a marker hidden there), which tracking joined to it.

This module checks and relabels one window; walking a take's windows with it (after the
take, or while it is tracked) and carrying relabellings back is verify_take.py.
"""

from __future__ import annotations

import numpy as np

from daemon.labelling.assign import (
    Compat,
    assign,
    body_scale,
    chain_groups,
    mirror_map,
    pair_stats,
    polish,
    to_marker_track,
)
from daemon.labelling.body import BodyTerms
from daemon.labelling.markerset import MarkerSet, signed_volume
from daemon.labelling.markerset_fit import check_fit
from daemon.labelling.moves import mirror_moves, module_moves, near_groups
from daemon.labelling.own import own_agrees
from daemon.labelling.start import link_window

WINDOW = 120          # frames per window (1 s at 120 Hz)
SUSPECT = 3.0         # a marker this many allowances off the set makes a window suspect
MARGIN = 5.0          # the new labels must score this much better (about 5 pairs' worth)
MARGIN_FULL = 20.0    # ... and those of the whole assignment from the set alone this much
MIN_SEEN = 0.3        # a marker seen in less of the window is not relabelled
STRIDE = 4            # every 4th window is checked (and its neighbours when it is wrong)
NEW_MISFIT = 2.0      # a track takes a new marker within 2 allowances (2 SD) of the set


def relabel_window(xyz: np.ndarray, ms: MarkerSet, noise_m: float = 0.003,
                   extra: np.ndarray | None = None, own: tuple | None = None
                   ) -> tuple[np.ndarray, np.ndarray] | None:
    """For a window's labelled positions (W, n, 3) and the tracks of its unlabelled
    points `extra` (E, W, 3): the new marker of each marker (n,) (-1: its label is taken
    from it) and the marker each unlabelled track takes (E,) (-1 none), or None when no
    other labelling scores clearly better. First the local search of the start's
    assignment from these labels (swaps, a part of the body mirrored, a module
    reordered, an unlabelled track taking a marker no track has: cheap, and what a
    tracker's errors mostly are); then, if the window still does not fit the set, the
    whole assignment from the set alone. New labels only reorder the labelled tracks'
    markers and give unlabelled tracks others: on a window with markers hidden the score
    gains by moving a label onto a marker seen in too few frames to be a track.
    `own`: this body's distances (mean, SD (n, n)) from labelled start frames, which
    outrank the set: new labels that fit them worse than the current ones are refused
    (a body built otherwise than the set's looks "wrong" to the set alone)."""
    W = len(xyz)
    tracks = np.nonzero(np.isfinite(xyz).all(2).sum(0) >= MIN_SEEN * W)[0]
    E = 0 if extra is None else len(extra)
    if len(tracks) + E < 3 or not len(tracks):
        return None
    X = np.ascontiguousarray(xyz[:, tracks].transpose(1, 0, 2))
    if E:
        X = np.concatenate([X, extra])
    cur = np.concatenate([tracks, np.full(E, -1)])
    keeps = _Keeps(cur, ms.n)
    before = check_fit(ms, xyz[::4], noise_m=noise_m)
    for _ in range(3):
        lab, gain = improve(X, ms, cur, noise_m, keeps)
        if gain < MARGIN or not keeps.labels(lab):
            lab = cur
        moved = _positions(X, lab, ms.n)
        fit = check_fit(ms, moved[::4], noise_m=noise_m)  # every 4th frame tells as much
        # a point tracking left unlabelled takes a marker only where it sits as the set
        # says (a wrong one scores too, by the set's loose allowance for far pairs)
        misfit = _misfits(fit, lab, cur, ms, before)
        if not misfit:
            break
        keeps.bar(misfit)
    else:
        lab, moved, fit = cur, xyz, before
    if fit.misfit and (fit.misfit_worst > SUSPECT or fit.bent or _turned(moved[::4], ms)):
        # from the set alone the assignment is less sure than tracking on a window with
        # markers hidden: it must win by more
        full, score = assign(X, ms, noise_m=noise_m)
        if keeps.labels(full) and score >= score_labels(X, ms, lab, noise_m) + MARGIN_FULL \
                and not _misfits(check_fit(ms, _positions(X, full, ms.n)[::4],
                                           noise_m=noise_m), full, cur, ms, before):
            lab = full
    if np.array_equal(lab, cur) or not own_agrees(X, lab, cur, own, ms.sd_m, noise_m):
        return None
    T = len(tracks)
    perm = np.arange(ms.n)
    taken = np.zeros(ms.n, bool)
    taken[lab[lab >= 0]] = True
    perm[taken] = -1              # a marker not in the window loses a label now taken
    perm[tracks] = lab[:T]
    return perm, lab[T:]


def _misfits(fit, lab: np.ndarray, cur: np.ndarray, ms: MarkerSet, before) -> list[int]:
    """The tracks `lab` labels anew against the set's word (check_fit's per-marker
    misfit, `before` that of `cur`): those given a marker placed more than NEW_MISFIT
    allowances off the set, unless the tracks relabelled fit better on the whole than
    before (a marker this body carries elsewhere, 85_02's RSHN, is off the set under its
    right name too, and its track fits worse under a wrong one)."""
    new = np.nonzero((lab >= 0) & (lab != cur))[0]
    z = np.array([fit.misfit.get(ms.labels[lab[t]], 0.0) for t in new])
    if not (z > NEW_MISFIT).any():
        return []
    was = [before.misfit.get(ms.labels[cur[t]], 0.0) for t in new if cur[t] >= 0]
    if was and z.mean() < np.mean(was):
        return []
    return [int(t) for t in new[z > NEW_MISFIT]]


class _Keeps:
    """Which labellings verification may move to from the labels `cur` (track ->
    marker, -1 unlabelled): every labelled track keeps a label and every marker held
    keeps a track; unlabelled tracks may take markers no track holds, except those
    `barred` (found not to fit)."""

    def __init__(self, cur: np.ndarray, n: int) -> None:
        self.cur = cur
        self.held = cur[cur >= 0]
        self.tracks = np.nonzero(cur >= 0)[0]
        self.barred = np.zeros(0, int)
        self.n = n

    def bar(self, tracks: list[int]) -> None:
        """Tracks that keep what they have: their label, or none."""
        self.barred = np.concatenate([self.barred, tracks]).astype(int)

    def __call__(self, mt: np.ndarray) -> bool:
        if not ((mt[self.held] >= 0).all() and np.isin(self.tracks, mt).all()):
            return False
        b = self.barred
        if not len(b):
            return True
        had = self.cur[b]
        return bool(np.all(np.where(had >= 0, mt[np.maximum(had, 0)] == b, ~np.isin(b, mt))))

    def labels(self, lab: np.ndarray) -> bool:
        mt = np.full(self.n, -1)
        got = lab >= 0
        mt[lab[got]] = np.nonzero(got)[0]
        return self(mt)


def _positions(X: np.ndarray, lab: np.ndarray, n: int) -> np.ndarray:
    """The window's labelled positions (W, n, 3) of tracks X (T, W, 3) labelled `lab`."""
    out = np.full((X.shape[1], n, 3), np.nan)
    got = lab >= 0
    out[:, lab[got]] = X[got].transpose(1, 0, 2)
    return out


def score_labels(X: np.ndarray, ms: MarkerSet, lab, noise_m: float = 0.003):
    """The whole-body score (as `assign` maximises it) of a given labelling `lab` (T,)
    of tracks X (T, W, 3), -1 for a track left unlabelled; a list of labellings: a list
    of scores (one table for all)."""
    D, S = pair_stats(X)
    judge = Compat(ms, D, S, body_scale(D, ms), noise_m)
    terms = BodyTerms(X, ms, noise_m=noise_m)
    out = []
    for one in (lab if isinstance(lab, list) else [lab]):
        P = np.zeros((len(X), ms.n))
        got = np.nonzero(one >= 0)[0]
        P[got, one[got]] = 1.0
        out.append(judge.score(P) + terms(to_marker_track(P)))
    return out if isinstance(lab, list) else out[0]


def improve(X: np.ndarray, ms: MarkerSet, lab: np.ndarray, noise_m: float = 0.003,
            allowed=None) -> tuple[np.ndarray, float]:
    """The labelling `lab` (T,) of tracks X (T, W, 3) improved by the local search of
    `assign` (swaps, mirror moves of a part of the body, every reordering inside a
    module, also of one whose shape fits), and how much its whole-body score rose: the
    cheap check of labels that tracking gave, which are right nearly always. `allowed`
    as for `polish`."""
    D, S = pair_stats(X)
    judge = Compat(ms, D, S, body_scale(D, ms), noise_m)
    terms = BodyTerms(X, ms, noise_m=noise_m)
    moves = [(p, -1) for p in mirror_moves(ms, mirror_map(ms.labels))] + module_moves(terms)
    P = np.zeros((len(X), ms.n))
    got = np.nonzero(lab >= 0)[0]
    P[got, lab[got]] = 1.0
    before = judge.score(P) + terms(to_marker_track(P))
    Q, after = polish(judge, P, terms, moves, allowed=allowed, every_order=True,
                      groups=near_groups(ms) + chain_groups(ms))
    out = np.full(len(X), -1)
    r, c = np.nonzero(Q)
    out[r] = c
    return out, after - before


def _turned(xyz: np.ndarray, ms: MarkerSet) -> bool:
    """Whether a handedness tetrahedron of the set is mirrored in most of the window's
    frames where it is seen (a side mirrored keeps every distance; only these tell)."""
    if not len(ms.chiral):
        return False
    v = signed_volume(xyz, ms.chiral)                                     # (W, q)
    seen = np.isfinite(v)
    wrong = (np.sign(v) != ms.chiral_sign[None]) & seen
    return bool((wrong.sum(0) > 0.5 * np.maximum(seen.sum(0), 1))[seen.sum(0) >= 5].any())


def window_labels(per_frame: list[np.ndarray], labels: dict, win: list[int], n: int,
                  extra: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A window's labelled positions (W, n, 3) from the labels (frame index -> (marker
    per point, confidence)), and its unlabelled points linked into tracks: positions
    (E, W, 3) and each track's point row per frame (E, W), -1 where it has none.
    Tracks seen in less than MIN_SEEN of the window (ghosts, mostly) are left out."""
    W = len(win)
    xyz = np.full((W, n, 3), np.nan)
    free, rows = [], []
    for w, i in enumerate(win):
        m = labels[i][0]
        got = m >= 0
        xyz[w, m[got][::-1]] = per_frame[i][got][::-1]    # a duplicate: its first point
        r = np.nonzero(~got)[0]
        rows.append(r)
        free.append(per_frame[i][r])
    if not extra or sum(len(r) for r in rows) < MIN_SEEN * W:
        return xyz, np.zeros((0, W, 3)), np.zeros((0, W), int)
    X, idx = link_window(free, min_seen=MIN_SEEN)
    out = np.full(idx.shape, -1)
    for w in range(W):
        got = idx[:, w] >= 0
        out[got, w] = rows[w][idx[got, w]]
    return xyz, X, out


def apply_window(labels: dict, win: list[int], perm: np.ndarray, gained: np.ndarray,
                 rows: np.ndarray) -> None:
    """Relabel a window in place: marker i becomes perm[i]; the points of unlabelled
    track e (rows (E, W)) take marker gained[e]."""
    new_tracks = np.nonzero(gained >= 0)[0]
    for w, i in enumerate(win):
        m, c = labels[i]
        new = np.where(m >= 0, perm[np.maximum(m, 0)], m)
        c = np.where(new >= 0, c, 0.0)
        r = rows[new_tracks, w]
        ok = r >= 0
        new[r[ok]] = gained[new_tracks[ok]]
        c[r[ok]] = 0.5
        labels[i] = (new, c)


def check_window(per_frame, labels, win, ms, noise_m, own=None):
    """Check one window and relabel it in place if it went wrong. Returns (perm, the
    markers the unlabelled tracks took, their positions (E, W, 3), their points' rows
    (E, W)) or None."""
    if len(win) < 10:
        return None
    xyz, X, rows = window_labels(per_frame, labels, win, ms.n)
    got = relabel_window(xyz, ms, noise_m, X, own)
    if got is None:
        return None
    perm, gained = got
    apply_window(labels, win, perm, gained, rows)
    return perm, gained, X, rows


def compose(first: np.ndarray | None, then: np.ndarray) -> np.ndarray:
    """The renaming `first` (marker i -> first[i], -1 dropped) followed by `then`."""
    if first is None:
        return then.copy()
    return np.where(first >= 0, then[np.maximum(first, 0)], -1)


def own_distances(xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """This body's distances between markers (n, n), mean and SD over a labelled window
    (W, n, 3); NaN for pairs not seen together."""
    return pair_stats(np.ascontiguousarray(xyz.transpose(1, 0, 2)))


def _own_fit(D: np.ndarray, lab: np.ndarray, ref: tuple[np.ndarray, np.ndarray],
             noise_m: float) -> float:
    """How well tracks' distances D (T, T) labelled `lab` fit the body's own distances
    `ref` (from a window whose labels are right): pairs within tolerance, as `Compat`
    counts them (1 a pair that fits)."""
    M, S = ref
    got = np.nonzero(lab >= 0)[0]
    d = D[np.ix_(got, got)]
    m = M[np.ix_(lab[got], lab[got])]
    tol = S[np.ix_(lab[got], lab[got])] + 2.0 * noise_m + 0.004
    e = (d - m) / tol
    ok = np.isfinite(e)
    return 0.5 * float(np.exp(-0.5 * e[ok] ** 2).sum())
