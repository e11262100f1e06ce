"""A take's labels verified window by window: after the take (verify_labels) or while it is
tracked (Verification), relabellings carried back to the windows that cannot tell by
themselves, and points no track held taken up.

Apart from daemon/labelling/verify.py, which checks and relabels one window against the
marker set; this module walks a take's windows with it and settles what neighbouring
windows say.
"""

from __future__ import annotations

import numpy as np

from daemon.labelling.assign import pair_stats
from daemon.labelling.markerset import MarkerSet
from daemon.labelling.verify import (
    MARGIN,
    MIN_SEEN,
    STRIDE,
    WINDOW,
    _own_fit,
    apply_window,
    check_window,
    compose,
    own_distances,
    score_labels,
    window_labels,
)


def carry_back(per_frame: list[np.ndarray], labels: dict, windows: list[list[int]],
               perm: np.ndarray, ms: MarkerSet, ref: tuple[np.ndarray, np.ndarray],
               noise_m: float = 0.003) -> int:
    """A relabelling found in a later window carried to the windows before it (nearest
    first), which tracking joined to it. Each is renamed when its tracks fit the body's
    own distances (`ref`, from the window that was relabelled) clearly better renamed;
    where those cannot tell (markers hidden there), when the renamed labels score
    within MARGIN of its own against the set (a loose fit cannot tell, and tracking
    joined it to a window that could). The first window that prefers its own labels,
    or whose tracks hold a marker the renaming drops, stops it. Returns the windows renamed."""
    done = 0
    for win in windows:
        xyz, _, _ = window_labels(per_frame, labels, win, ms.n, extra=False)
        count = np.isfinite(xyz).all(2).sum(0)
        tracks = np.nonzero(count >= MIN_SEEN * len(win))[0]
        seen = np.nonzero(count)[0]
        if (perm[tracks] < 0).any() or np.array_equal(perm[seen], seen):
            break
        if len(win) >= 10:              # (a few frames cannot tell)
            X = np.ascontiguousarray(xyz[:, tracks].transpose(1, 0, 2))
            D, _ = pair_stats(X)
            own = _own_fit(D, perm[tracks], ref, noise_m) - _own_fit(D, tracks, ref, noise_m)
            if own < -MARGIN:
                break
            if own < MARGIN:
                old_score, new_score = score_labels(X, ms, [tracks, perm[tracks]], noise_m)
                if new_score < old_score - MARGIN:
                    break
        apply_window(labels, win, perm, np.zeros(0, int), np.zeros((0, len(win)), int))
        done += 1
    return done


def taken_up(gained: np.ndarray, X: np.ndarray, per_frame: list[np.ndarray], labels: dict,
             win: list[int], n: int) -> tuple | None:
    """What the tracker needs to follow the markers unlabelled tracks took in a window
    it has just labelled (ending at its frame): per marker its last point in the window,
    its motion a frame, how many frames ago, and where the (relabelled) window had every
    marker then (`Labeller.found`); None if no track took one."""
    e = np.nonzero(gained >= 0)[0]
    if not len(e):
        return None
    seen = np.isfinite(X[e]).all(2)                                       # (m, W)
    last = len(win) - 1 - np.argmax(seen[:, ::-1], axis=1)
    m = np.arange(len(e))
    before = np.maximum(last - 1, 0)
    ok = seen[m, before] & (last > 0)
    xyz = X[e, last]
    vel = np.where(ok[:, None], xyz - X[e, before], 0.0)
    window = window_labels(per_frame, labels, win, n, extra=False)[0]        # relabelled
    return gained[e], xyz, vel, len(win) - 1 - last, window[last]


def verify_labels(per_frame: list[np.ndarray], labels: dict, frames: range, ms: MarkerSet,
                  width: int = WINDOW, stride: int = STRIDE, noise_m: float = 0.003,
                  own: tuple | None = None) -> int:
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
            done[k] = check_window(per_frame, labels, win, ms, noise_m, own) is not None
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
    back to one that is right, and the tracker is told (`Labeller.relabel`, and
    `Labeller.found` for markers an unlabelled track took), so that it carries the right
    labels on and forgets the distances it learned from wrong ones."""

    def __init__(self, ms: MarkerSet, per_frame: list[np.ndarray], labels: dict,
                 width: int = WINDOW, stride: int = STRIDE, noise_m: float = 0.003,
                 own: tuple | None = None, new_tracker=None) -> None:
        self.ms, self.per_frame, self.labels = ms, per_frame, labels
        self.own = own            # the body's distances from labelled start frames
        self.new_tracker = new_tracker    # a fresh Labeller, to track again from a window
        self.width, self.stride, self.noise_m = width, stride, noise_m
        self.windows: list[list[int]] = []
        self.right: dict[int, bool] = {}
        self.fixed = 0
        self.head: np.ndarray | None = None     # the renaming the first window took
        self.head_ref: tuple | None = None      # ... and the body's distances it fits

    def _fix(self, k: int):
        got = check_window(self.per_frame, self.labels, self.windows[k], self.ms,
                            self.noise_m, self.own)
        self.right[k] = got is None
        self.fixed += got is not None
        return got

    def after(self, lab, order: list[int], n_done: int) -> None:
        """Call after frame order[n_done] was labelled by `lab`."""
        if (n_done + 1) % self.width:
            return
        self.windows.append(order[n_done + 1 - self.width:n_done + 1])
        k = len(self.windows) - 1
        if k % self.stride == 0 or not self.right.get(k - 1, True):
            self._check(lab, k)
        if lab.own_spread:
            # the window's labels, checked or not, tell how much this body moves each
            # distance: ten labelled start frames do not (NeighbourEvidence.learn_spread)
            lab.learn_spread(window_labels(self.per_frame, self.labels, self.windows[k],
                                           self.ms.n, extra=False)[0])

    def _check(self, lab, k: int) -> None:
        got = self._fix(k)
        if got is None:
            return
        perm, gained, X, _ = got
        lab.relabel(perm)
        found = taken_up(gained, X, self.per_frame, self.labels, self.windows[k], self.ms.n)
        if found is not None:
            lab.found(*found)
        # the windows before it back to a right one: checked if they were not, and
        # renamed as this one was if they cannot tell
        b, src = k - 1, k
        while b >= 0 and b not in self.right:
            got = self._fix(b)
            if got is None:
                break
            perm, src = got[0], b
            b -= 1
        if src < k:
            self._retrack(lab, k)
        ref = own_distances(window_labels(self.per_frame, self.labels, self.windows[src],
                                          self.ms.n, extra=False)[0])
        if b < 0 or carry_back(self.per_frame, self.labels,
                               [self.windows[j] for j in range(b, -1, -1)], perm, self.ms,
                               ref, self.noise_m) == b + 1:
            self.head = compose(self.head, perm)
            self.head_ref = ref

    def _retrack(self, lab, k: int) -> None:
        """Window k and the one before it were both relabelled, each by its own search
        from the set; where the two disagree (the same tracks renamed otherwise), the
        window that saw more of the body decides. A body built otherwise than the set's
        makes the set's choice close on a window with markers hidden: on one body
        window k-1 (every marker seen) found the right leg, and window k (a hip marker
        hidden) the leg's labels shifted by one marker, 5 units better by the set; the
        tracker carried window k's on to the end. So when window k-1 holds more evidence
        (its labels score higher against the set), window k is tracked again from
        k-1's labels, checked with k-1's distances as this body's own (a label the set
        proposes must agree with them), and the tracker goes on from there."""
        if self.new_tracker is None or k < 1:
            return
        n = self.ms.n
        prev = window_labels(self.per_frame, self.labels, self.windows[k - 1], n, extra=False)[0]
        here = window_labels(self.per_frame, self.labels, self.windows[k], n, extra=False)[0]
        if _evidence(prev, self.ms, self.noise_m) <= _evidence(here, self.ms, self.noise_m):
            return
        new = self.new_tracker()
        new.start_from_labelled_frames(prev)
        kept = {i: self.labels[i] for i in self.windows[k]}
        for i in self.windows[k]:
            self.labels[i] = new.update(self.per_frame[i])
        if _agree(kept, self.labels, self.windows[k]):
            self.labels.update(kept)
            return
        ref = own_distances(prev)
        got = check_window(self.per_frame, self.labels, self.windows[k], self.ms,
                           self.noise_m, self.own if self.own is not None else ref)
        if got is not None:
            perm, gained, X, _ = got
            new.relabel(perm)
            found = taken_up(gained, X, self.per_frame, self.labels, self.windows[k], n)
            if found is not None:
                new.found(*found)
        lab.take_state(new)

    def finish(self, lab, order: list[int]) -> None:
        """The frames after the last full window, and a last check of the take's end."""
        tail = order[len(self.windows) * self.width:]
        if tail:
            self.windows.append(list(tail))
        if self.windows and (len(self.windows) - 1) not in self.right:
            self._check(lab, len(self.windows) - 1)


def _evidence(xyz: np.ndarray, ms: MarkerSet, noise_m: float) -> float:
    """How much a labelled window (W, n, 3) tells: the set's whole-body score of its
    labels (markers seen in MIN_SEEN of it), which grows with the pairs it sees."""
    count = np.isfinite(xyz).all(2).sum(0)
    tracks = np.nonzero(count >= MIN_SEEN * len(xyz))[0]
    if len(tracks) < 3:
        return 0.0
    X = np.ascontiguousarray(xyz[:, tracks].transpose(1, 0, 2))
    return float(score_labels(X, ms, tracks, noise_m))


def _agree(a: dict, b: dict, win: list[int]) -> bool:
    """Whether two labellings of a window's frames name every point alike."""
    return all(np.array_equal(a[i][0], b[i][0]) for i in win)
