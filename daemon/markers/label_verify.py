"""Verifying a take's labels window by window and relabelling where they went wrong.

Tracking carries a wrong labelling on as faithfully as a right one: a leg's labels
shifted by one marker, a side mirrored at the pelvis, two markers swapped after a long
occlusion all keep their distances from frame to frame, and the take's own distances,
learned as it goes, follow them. Only the marker set still says they are wrong. So each
window of frames is compared with the set (daemon/markers/markerset_fit.py: a marker
whose distances to its steadiest neighbours are far outside the allowance for another
subject, a rigid segment that bends; and a handedness tetrahedron mirrored in most of
the window's frames); where one is, the window's labelled trajectories
are labelled again by the same global assignment that starts a take from the set alone
(daemon/markers/label_assign.py), and the new labels are taken when they score clearly
better than the labels tracking gave. Every window first gets the assignment's local
search from its current labels, which is cheap and finds a side mirrored at the pelvis
(which no distance and, on the CMU set, no handedness tetrahedron shows by itself).
"""

from __future__ import annotations

import numpy as np

from daemon.markers.label_assign import (
    BodyTerms,
    Compat,
    assign,
    body_scale,
    mirror_map,
    mirror_moves,
    module_moves,
    pair_stats,
    polish,
    to_marker_track,
)
from daemon.markers.markerset import MarkerSet, signed_volume
from daemon.markers.markerset_fit import check_fit

WINDOW = 120          # frames per window (1 s at 120 Hz)
SUSPECT = 3.0         # a marker this many allowances off the set makes a window suspect
MARGIN = 5.0          # the new labels must score this much better (about 5 pairs' worth)
MARGIN_FULL = 20.0    # ... and those of the whole assignment from the set alone this much
MIN_SEEN = 0.3        # a marker seen in less of the window is not relabelled
STRIDE = 4            # every 4th window is checked (and its neighbours when it is wrong)


def relabel_window(xyz: np.ndarray, ms: MarkerSet, noise_m: float = 0.003
                   ) -> np.ndarray | None:
    """For a window's labelled positions (W, n, 3): the new marker of each marker (n,)
    (-1: its label is taken from it), or None when no other labelling scores clearly
    better. First the local search of the start's assignment from these labels (swaps,
    a part of the body mirrored, a module reordered: cheap, and what a tracker's errors
    mostly are); then, if the window still does not fit the set, the whole assignment
    from the set alone."""
    W = len(xyz)
    tracks = np.nonzero(np.isfinite(xyz).all(2).sum(0) >= MIN_SEEN * W)[0]
    if len(tracks) < 3:
        return None
    X = np.ascontiguousarray(xyz[:, tracks].transpose(1, 0, 2))
    lab, gain = improve(X, ms, tracks, noise_m)
    # only the tracks' labels reordered is taken: on a window with markers hidden the
    # score gains by moving a label onto a marker seen in too few frames to be a track
    if gain < MARGIN or not _reordered(lab, tracks):
        lab, gain = tracks, 0.0
    if not np.array_equal(lab, tracks):
        moved = xyz.copy()
        moved[:, tracks] = np.nan
        moved[:, lab[lab >= 0]] = xyz[:, tracks[lab >= 0]]
    else:
        moved = xyz
    fit = check_fit(ms, moved[::4], noise_m=noise_m)      # every 4th frame tells as much
    if fit.misfit and (fit.misfit_worst > SUSPECT or fit.bent or _turned(moved[::4], ms)):
        # from the set alone the assignment is less sure than tracking on a window with
        # markers hidden: it must win by more
        full, score = assign(X, ms, noise_m=noise_m)
        if _reordered(full, tracks) and \
                score >= score_labels(X, ms, lab, noise_m) + MARGIN_FULL:
            lab = full
    if np.array_equal(lab, tracks):
        return None
    perm = np.arange(ms.n)
    taken = np.zeros(ms.n, bool)
    taken[lab[lab >= 0]] = True
    perm[taken] = -1              # a marker not in the window loses a label now taken
    perm[tracks] = lab
    return perm


def score_labels(X: np.ndarray, ms: MarkerSet, lab: np.ndarray, noise_m: float = 0.003
                 ) -> float:
    """The whole-body score (as `assign` maximises it) of a given labelling `lab` (T,)
    of tracks X (T, W, 3), -1 for a track left unlabelled."""
    D, S = pair_stats(X)
    judge = Compat(ms, D, S, body_scale(D, ms), noise_m)
    P = np.zeros((len(X), ms.n))
    got = np.nonzero(lab >= 0)[0]
    P[got, lab[got]] = 1.0
    return judge.score(P) + BodyTerms(X, ms, noise_m=noise_m)(to_marker_track(P))


def improve(X: np.ndarray, ms: MarkerSet, lab: np.ndarray, noise_m: float = 0.003
            ) -> tuple[np.ndarray, float]:
    """The labelling `lab` (T,) of tracks X (T, W, 3) improved by the local search of
    `assign` (swaps, mirror moves of a part of the body, reorderings inside a module),
    and how much its whole-body score rose: the cheap check of labels that tracking
    gave, which are right nearly always."""
    D, S = pair_stats(X)
    judge = Compat(ms, D, S, body_scale(D, ms), noise_m)
    terms = BodyTerms(X, ms, noise_m=noise_m)
    moves = [(p, -1) for p in mirror_moves(ms, mirror_map(ms.labels))] + module_moves(terms)
    P = np.zeros((len(X), ms.n))
    got = np.nonzero(lab >= 0)[0]
    P[got, lab[got]] = 1.0
    before = judge.score(P) + terms(to_marker_track(P))
    Q, after = polish(judge, P, terms, moves)
    out = np.full(len(X), -1)
    r, c = np.nonzero(Q)
    out[r] = c
    return out, after - before


def _reordered(lab: np.ndarray, tracks: np.ndarray) -> bool:
    """Whether `lab` gives the tracks their own labels in another order."""
    return bool(np.array_equal(np.sort(lab), np.sort(tracks)))


def _turned(xyz: np.ndarray, ms: MarkerSet) -> bool:
    """Whether a handedness tetrahedron of the set is mirrored in most of the window's
    frames where it is seen (a side mirrored keeps every distance; only these tell)."""
    if not len(ms.chiral):
        return False
    v = signed_volume(xyz, ms.chiral)                                     # (W, q)
    seen = np.isfinite(v)
    wrong = (np.sign(v) != ms.chiral_sign[None]) & seen
    return bool((wrong.sum(0) > 0.5 * np.maximum(seen.sum(0), 1))[seen.sum(0) >= 5].any())


def verify_labels(per_frame: list[np.ndarray], labels: dict, frames: range, ms: MarkerSet,
                  width: int = WINDOW, stride: int = STRIDE, noise_m: float = 0.003) -> int:
    """Check the labels (frame index -> (marker per point, confidence)) over `frames`,
    every `stride`-th window of `width` frames, and relabel, in place, a window whose
    labels the set says are wrong, with the windows before it back to one that is
    right (the frames since it went wrong) and the windows after it until one is right.
    Returns the number of windows relabelled."""
    idx = list(frames)
    starts = list(range(0, max(1, len(idx) - width // 2), width))
    done: dict[int, bool] = {}

    def fix(k: int) -> bool:
        if k not in done:
            win = idx[starts[k]:starts[k] + width]
            if k == len(starts) - 1:
                win = idx[starts[k]:]
            xyz = np.full((len(win), ms.n, 3), np.nan)
            for w, i in enumerate(win):
                m = labels[i][0]
                got = m >= 0
                xyz[w, m[got][::-1]] = per_frame[i][got][::-1]
            perm = relabel_window(xyz, ms, noise_m) if len(win) >= 10 else None
            done[k] = perm is not None
            if perm is not None:
                for i in win:
                    m, c = labels[i]
                    new = np.where(m >= 0, perm[np.maximum(m, 0)], m)
                    labels[i] = (new, np.where(new >= 0, c, 0.0))
        return done[k]

    for k in range(0, len(starts), stride):
        if fix(k):
            b = k - 1
            while b >= 0 and fix(b):
                b -= 1
            f = k + 1
            while f < len(starts) and fix(f):
                f += 1
    return sum(done.values())


class Verification:
    """Verification while a take is tracked: after every `width` frames the last window
    (every `stride`-th) is checked; a wrong one is relabelled, with the windows before it
    back to one that is right, and the tracker is told (`Labeller.relabel`), so that it
    carries the right labels on and forgets the distances it learned from wrong ones."""

    def __init__(self, ms: MarkerSet, per_frame: list[np.ndarray], labels: dict,
                 width: int = WINDOW, stride: int = STRIDE, noise_m: float = 0.003) -> None:
        self.ms, self.per_frame, self.labels = ms, per_frame, labels
        self.width, self.stride, self.noise_m = width, stride, noise_m
        self.windows: list[list[int]] = []
        self.right: dict[int, bool] = {}
        self.fixed = 0

    def _fix(self, k: int) -> np.ndarray | None:
        win = self.windows[k]
        xyz = np.full((len(win), self.ms.n, 3), np.nan)
        for w, i in enumerate(win):
            m = self.labels[i][0]
            got = m >= 0
            xyz[w, m[got][::-1]] = self.per_frame[i][got][::-1]
        perm = relabel_window(xyz, self.ms, self.noise_m) if len(win) >= 10 else None
        self.right[k] = perm is None
        if perm is not None:
            self.fixed += 1
            for i in win:
                m, c = self.labels[i]
                new = np.where(m >= 0, perm[np.maximum(m, 0)], m)
                self.labels[i] = (new, np.where(new >= 0, c, 0.0))
        return perm

    def after(self, lab, order: list[int], n_done: int) -> None:
        """Call after frame order[n_done] was labelled by `lab`."""
        if (n_done + 1) % self.width:
            return
        self.windows.append(order[n_done + 1 - self.width:n_done + 1])
        k = len(self.windows) - 1
        if k % self.stride == 0 or not self.right.get(k - 1, True):
            self._check(lab, k)

    def _check(self, lab, k: int) -> None:
        perm = self._fix(k)
        if perm is None:
            return
        lab.relabel(perm)
        b = k - 1
        while b >= 0 and b not in self.right and self._fix(b) is not None:
            b -= 1

    def finish(self, lab, order: list[int]) -> None:
        """The frames after the last full window, and a last check of the take's end."""
        tail = order[len(self.windows) * self.width:]
        if tail:
            self.windows.append(list(tail))
        if self.windows and (len(self.windows) - 1) not in self.right:
            self._check(lab, len(self.windows) - 1)
