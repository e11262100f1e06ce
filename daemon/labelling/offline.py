"""Labelling a whole take: the start (labelled frames, or a window from the set alone),
then the tracker forward to the end and backward to the first frame; and the take-level
figures about duplicates."""

from __future__ import annotations

import sys

import numpy as np

from calibkit.core.blas import one_blas_thread
from daemon.formats.c3dio import Points, Take
from daemon.labelling.assign import pair_stats
from daemon.labelling.extend import extend_runs
from daemon.labelling.extras import unlabelled_tracks, with_extras
from daemon.labelling.labeller import Labeller
from daemon.labelling.markerset import MarkerSet
from daemon.labelling.markerset_fit import check_fit
from daemon.labelling.start import window_start
from daemon.labelling.verify import (
    MARGIN,
    MIN_SEEN,
    WINDOW,
    improve,
    score_labels,
    window_labels,
)
from daemon.labelling.verify_take import Verification, carry_back, verify_labels

KERNELS_FROM = 8000      # frames from which loading the compiled kernels pays off
BETTER_PER_PAIR = 0.1    # a window explained this much better a pair is better evidence
TRUSTED_PER_PAIR = 0.8   # a start window explained this well a pair (right: 0.88-0.95,
#                          scrambled by the search: 0.52) may declare markers the set lacks


def label_take(points: Points, ms: MarkerSet, rate_hz: float = 120.0,
               start_labels: Take | None = None, start_frames: int = 0, progress=None,
               options: dict | None = None, from_window: bool = True,
               verify: bool = True) -> tuple[Take, np.ndarray, np.ndarray]:
    """Label every frame of `points`. With `start_labels` (a labelled take) its first
    `start_frames` frames are taken as they are and tracking starts after them; without,
    a window of frames is labelled from the marker set alone (`from_window`; otherwise
    the first frame, as the live labeller does). With `verify` the labels are then
    checked against the set window by window, and a window whose labels went wrong is
    labelled again (daemon/labelling/verify.py). Returns the labelled take, per-frame
    confidence (mean over labelled markers) and the per-point labels (aligned with points
    rows after sorting by frame, see `Points.split`). Small matrices throughout: one
    BLAS thread (calibkit/core/blas.py)."""
    with one_blas_thread():
        return _label_take(points, ms, rate_hz, start_labels, start_frames, progress,
                           options, from_window, verify)


def _label_take(points, ms, rate_hz, start_labels, start_frames, progress, options,
                from_window, verify):
    frames, per_frame = points.split()
    options = dict(options or {})
    # the compiled kernels cost ~0.4 s of CPU to load and save ~0.05 ms a frame: on a
    # shorter take their numpy twins are faster (unless the kernels are loaded already)
    options.setdefault("compiled", len(per_frame) >= KERNELS_FROM
                       or "daemon.labelling.kernels" in sys.modules)
    lab = Labeller(ms, rate_hz, **options)
    n_frames = int(frames[-1] - frames[0] + 1) if len(frames) else 0
    first = int(frames[0]) if len(frames) else 0
    xyz = np.full((n_frames, ms.n, 3), np.nan)
    conf = np.zeros(n_frames)
    labels_out = []
    start = 0
    own = None            # this body's distances from labelled start frames: they outrank the set
    tracked = ms          # the set the tracker follows: with the start's markers the set lacks
    if start_labels is not None and start_frames > 0:
        s = start_labels.select(ms.labels)
        use = min(start_frames, s.n_frames)
        sx = s.xyz_m[:use]
        # points the start leaves unlabelled that last through it: markers the set lacks,
        # tracked as markers of their own so that no marker of the set takes them
        extra = unlabelled_tracks(start_points(frames, per_frame, s.first_frame, sx,
                                               lab.merge_m), sx, lab.merge_m, ms)
        if len(extra):
            tracked = with_extras(ms, sx, extra)
            sx = np.concatenate([sx, extra.transpose(1, 0, 2)], axis=1)
            lab = Labeller(tracked, rate_hz, **options)
        lab.start_from_labelled_frames(sx)
        own = start_distances(sx, tracked, lab.noise_m)
        sx = sx[:, :ms.n]
        fidx = np.arange(use) + s.first_frame - first
        keep = (fidx >= 0) & (fidx < n_frames)
        xyz[fidx[keep]] = sx[keep]
        conf[fidx[keep]] = 1.0
        start = int(np.searchsorted(frames, s.first_frame + use))
        for f in range(start):
            labels_out.append(np.full(len(per_frame[f]), -2))
    out: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    order = list(range(start, len(frames)))
    window = None
    if start == 0 and len(frames) and from_window:
        # from the marker set alone: one global assignment on a window of frames
        # (daemon/labelling/start.py), handed to the tracker as labelled start frames
        unfit: list[np.ndarray] = []
        window = window_start(per_frame, ms, noise_m=lab.noise_m, merge_m=lab.merge_m,
                              unfit=unfit)
        if unfit and _evidence(window[2], ms, lab.noise_m)[1] >= TRUSTED_PER_PAIR:
            # tracks the assignment found to fit no marker of the set (markers the set
            # lacks): tracked as markers of their own, as a labelled start's would be,
            # where the window's labels are explained well (a start the search scrambled
            # left a real marker out: the tracker then never named it, 99.96 -> 80.8 %)
            extra = np.stack(unfit)
            tracked = with_extras(ms, window[2], extra)
            window = (window[0], window[1],
                      np.concatenate([window[2], extra.transpose(1, 0, 2)], axis=1))
            lab = Labeller(tracked, rate_hz, **options)
        order = _from_window(lab, per_frame, out, window,
                             lambda: Labeller(tracked, rate_hz, **options))
    check = _track(lab, per_frame, out, order, start, tracked, own, verify, progress,
                   lambda: Labeller(tracked, rate_hz, **options))
    if window is not None and check is not None and check.fixed:
        # verification had to relabel windows: the start's own window may have been
        # labelled wrong (a marker hidden in it, its place taken by a neighbour, which
        # the set scores higher on a body built otherwise). A window verification left
        # holding more of the set's markers than the start did, or explained clearly
        # better by the set, is better evidence:
        # the take is labelled again from it, forward and backward
        again = _better_window(per_frame, out, range(start, len(frames)), window, tracked,
                               lab.noise_m)
        if again is not None:
            out = {}
            lab = Labeller(tracked, rate_hz, **options)
            order = _from_window(lab, per_frame, out, again,
                                 lambda: Labeller(tracked, rate_hz, **options))
            _track(lab, per_frame, out, order, start, tracked, own, verify, None,
                   lambda: Labeller(tracked, rate_hz, **options))
    # runs carried over the points that continue them (the tracker holds a marker back
    # for a few frames after it comes back; those frames hold its point all the same)
    marks = [out[i][0].copy() if i >= start else np.zeros(0, int) for i in range(len(frames))]
    if extend_runs(frames, per_frame, marks, start):
        for i in range(start, len(frames)):
            m, c = out[i]
            if not np.array_equal(marks[i], m):
                new = (marks[i] >= 0) & (marks[i] != m)
                out[i] = (marks[i], np.where(marks[i] < 0, 0.0, np.where(new, 0.5, c)))
    for i in range(start, len(frames)):
        P = per_frame[i]
        m, c = out[i]
        if tracked.n > ms.n:            # markers the set lacks: unlabelled in the output
            m = np.where(m < ms.n, m, -1)
            c = np.where(m >= 0, c, 0.0)
        fi = int(frames[i] - first)
        got = m >= 0
        xyz[fi, m[got][::-1]] = P[got][::-1]      # a duplicate: its first point
        conf[fi] = float(c[got].mean()) if got.any() else 0.0
        labels_out.append(m)
    take = Take(list(ms.labels), xyz, rate_hz, first)
    return take, conf, labels_out


def start_points(frames: np.ndarray, per_frame: list[np.ndarray], first: int,
                 xyz: np.ndarray, within_m: float) -> list[np.ndarray]:
    """The points (k, 3) of each labelled start frame (xyz (W, n, 3), numbered from
    `first`): those of the points' frame of that number, or of the one beside it, that
    holds the labelled positions (two files may number a take's frames from 0 and 1);
    none where no frame holds at least half of them (no evidence)."""
    out = []
    for f in range(len(xyz)):
        L = xyz[f][np.isfinite(xyz[f]).all(1)]
        best, pts = 0, np.zeros((0, 3))
        for a in np.searchsorted(frames, first + f) + np.array([0, -1, 1]):
            if not 0 <= a < len(frames) or not len(L) or not len(per_frame[a]):
                continue
            d = np.linalg.norm(per_frame[a][:, None] - L[None], axis=2)
            held = int((d.min(0) <= within_m).sum())
            if held > best:
                best, pts = held, per_frame[a]
        out.append(pts if best >= 0.5 * len(L) else np.zeros((0, 3)))
    return out


def _from_window(lab: Labeller, per_frame: list[np.ndarray], out: dict, window: tuple,
                 new_tracker) -> list[int]:
    """Start `lab` from a labelled window (first frame, its frames' labels, its labelled
    positions (W, n, 3)): the tracker learns this body's distances and shapes from the
    whole window, then labels the window itself from its first two frames (markers the
    start left out, e.g. hidden for most of the window, are found on the way); the frames
    before the window are labelled backward by a second tracker. Returns the frames left
    to track forward."""
    w0, wl, wx = window
    lab.start_from_labelled_frames(wx)
    S = min(2, len(wl))
    lab.start_from_labelled(wx[0])
    if S > 1:
        lab.update_labelled(wx[1])
    for w in range(S):
        out[w0 + w] = (wl[w], np.where(wl[w] >= 0, 0.5, 0.0))
    if w0 > 0:
        back = new_tracker()
        back.start_from_labelled_frames(wx[::-1])
        for i in range(w0 - 1, -1, -1):
            out[i] = back.update(per_frame[i])
    return list(range(w0 + S, len(per_frame)))


def _track(lab: Labeller, per_frame: list[np.ndarray], out: dict, order: list[int],
           start: int, ms: MarkerSet, own, verify: bool, progress, new_tracker
           ) -> Verification | None:
    """Track `order` forward with `lab`, verifying window by window; then the frames
    before the first of `order` (labelled backward) get the renamings verification
    made and a check of their own. Returns the verification (None without)."""
    check = Verification(ms, per_frame, out, noise_m=lab.noise_m, own=own,
                         new_tracker=new_tracker) if verify else None
    for n_done, i in enumerate(order):
        out[i] = lab.update(per_frame[i])
        if check is not None:
            check.after(lab, order, n_done)
        if progress is not None and n_done % 200 == 0:
            progress.update(n_done)
    if check is not None:
        check.finish(lab, order)
        if order and order[0] > start:      # the frames before the window, labelled backward
            if check.head is not None:      # ... from the start's labels, renamed since
                ahead = list(range(start, order[0]))[::-1]
                back = [ahead[j:j + check.width][::-1] for j in range(0, len(ahead), check.width)]
                carry_back(per_frame, out, back, check.head, ms, check.head_ref, lab.noise_m)
            # (windows relabelled there count as verification's too: see _better_window)
            check.fixed += verify_labels(per_frame, out, range(start, order[0]), ms,
                                         noise_m=lab.noise_m)
    return check


def _evidence(xyz: np.ndarray, ms: MarkerSet, noise_m: float) -> tuple[int, float]:
    """What a labelled window (W, n, 3) says for its labels: the markers it holds (seen in
    MIN_SEEN of its frames) and the set's whole-body score of them per pair of those."""
    held = np.isfinite(xyz).all(2).sum(0) >= MIN_SEEN * len(xyz)
    k = int(held.sum())
    if k < 3:
        return k, 0.0
    X = np.ascontiguousarray(xyz[:, held].transpose(1, 0, 2))
    return k, float(score_labels(X, ms, np.nonzero(held)[0], noise_m)) / (k * (k - 1) / 2)


def _better_window(per_frame: list[np.ndarray], out: dict, frames: range,
                   start: tuple, ms: MarkerSet, noise_m: float) -> tuple | None:
    """Among the take's windows of WINDOW frames over `frames` (their final labels: the
    start's own frames tracked on, the frames before the start tracked backward,
    windows relabelled by verification on either side), the one that is better evidence
    than the start's window was: one holding more of the set's markers, or nearly as
    many (90 %) with labels the set explains clearly better (BETTER_PER_PAIR a pair: a
    start scrambled by the search on a crouched posture scored 0.52 a pair, the right
    labels of a later window with one marker hidden 0.95). The frames before the start
    count as much as those after it: two bodies' starts (frames 600-719 of 85_02, the
    crouch) came out scrambled, and the windows verification put right were before
    them. Returned as a start (first frame, labels, labelled positions), else None."""
    best = None
    held0, per_pair0 = _evidence(start[2], ms, noise_m)
    idx = list(frames)
    for a in range(0, len(idx) - WINDOW + 1, WINDOW):
        win = idx[a:a + WINDOW]
        xyz = window_labels(per_frame, out, win, ms.n, extra=False)[0]
        held, per_pair = _evidence(xyz, ms, noise_m)
        if held <= held0 and (per_pair < per_pair0 + BETTER_PER_PAIR or held < 0.9 * held0):
            continue
        if best is None or (held, per_pair) > best[0]:
            best = ((held, per_pair), (win[0], [out[i][0] for i in win], xyz))
    return None if best is None else best[1]


def duplicate_trajectories(take: Take, within_m: float = 0.006, share: float = 0.9
                           ) -> list[tuple[str, str, int]]:
    """Pairs of a file's trajectories that are one marker stored twice: within
    `within_m` of each other in at least `share` of the frames both are seen (and in at
    least 3 frames). Returns (name, twin, frames together) for each pair."""
    x = take.xyz_m
    out = []
    for i in range(len(take.labels)):
        d = np.linalg.norm(x[:, i + 1:] - x[:, i:i + 1], axis=2)       # (F, n - i - 1)
        both = np.isfinite(d).sum(0)
        close = (d < within_m).sum(0)
        for j in np.nonzero((both >= 3) & (close >= share * np.maximum(both, 1)))[0]:
            out.append((take.labels[i], take.labels[i + 1 + j], int(both[j])))
    return out


def merged_points(labels_per_frame: list[np.ndarray]) -> int:
    """Points labelled as a marker another point of their frame already is (duplicates
    taken as one)."""
    return int(sum(int((m >= 0).sum()) - len(np.unique(m[m >= 0])) for m in labels_per_frame))


def start_distances(xyz: np.ndarray, ms, noise_m: float = 0.003,
                    trust: float = 3.0) -> tuple[np.ndarray, np.ndarray] | None:
    """This body's distances (mean, SD (n, n)) from labelled start frames (f, n, 3), for
    `own_agrees`, or None where the start is not to be trusted. A labelled start can
    itself be wrong (a leg's labels shifted by one marker, a pelvis mirrored): where the
    set's local search (verification's, daemon/labelling/verify.py) relabels the
    start frames themselves, they vouch for nothing; and a marker more than `trust`
    allowances off the set there (markerset_fit's misfit; a body re-proportioned by
    15 % sits within 1-3) is not vouched for: the set decides about it."""
    X = np.ascontiguousarray(xyz.transpose(1, 0, 2))
    seen = np.isfinite(X).all(2).any(1)
    lab = np.where(seen, np.arange(ms.n), -1)
    got, gain = improve(np.where(seen[:, None, None], X, np.nan)[seen], ms, lab[seen],
                        noise_m)
    if gain >= MARGIN and not np.array_equal(got, lab[seen]):
        return None
    M, S = pair_stats(X)
    fit = check_fit(ms, xyz, noise_m=noise_m)
    off = np.array([fit.misfit.get(name, 0.0) > trust for name in ms.labels])
    M = M.copy()
    M[off] = np.nan
    M[:, off] = np.nan
    return M, S
