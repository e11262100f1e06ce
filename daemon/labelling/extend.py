"""Labelled runs carried over the unlabelled points that continue them, frame by frame.

Why: the tracker meets a marker that comes back from hiding going forward in time only,
and holds it back until its neighbours or its module tell it apart (a foot's toe beside
its fifth metatarsal, both just back; a marker never seen before whose module is the
set's shape, not this body's). A few frames later it is taken, and from then on its run
is labelled; the frames before hold the same point, moving on the same path, unlabelled.
Labelling from the set alone goes over the take backward from its start window as well,
and so met those frames with the marker already tracked: a correct labelled start ended
below the set alone on a few bodies by exactly such runs (docs/labelling_subjects.md).
Here every run is carried back (and forward) over points that continue its motion: the
point nearest the run's linear extrapolation, within GATE_M, with no other unlabelled
point, and no other run's extrapolation, within CLEAR times that distance or the gate.
"""

from __future__ import annotations

import numpy as np

GATE_M = 0.010  # the extrapolation's error a frame at 120 fps: about 1.5 mm at 20 m/s^2
CLEAR = 3.0     # the runner-up point (or run) at least this many times farther


def extend_runs(frames: np.ndarray, per_frame: list[np.ndarray], marker_of: list[np.ndarray],
                first: int = 0, gate_m: float = GATE_M, clear: float = CLEAR) -> int:
    """Extend each marker's labelled runs over frames `first`.. (indices into
    `per_frame`), backward then forward, in place: `marker_of[i]` is frame i's marker per
    point (-1 unlabelled). Only consecutive frame numbers are joined. Returns the points
    labelled (a glitch replaced by its run's point counts as one)."""
    F = len(per_frame)
    if F - first < 3:
        return 0
    n = 1 + max((int(m.max()) for m in marker_of[first:] if len(m)), default=-1)
    if n <= 0:
        return 0
    point = np.full((F, n), -1, dtype=np.int64)   # each marker's point in each frame
    sizes = np.array([len(m) for m in marker_of[first:]])
    if sizes.sum():
        m = np.concatenate(marker_of[first:])
        fi = np.repeat(np.arange(first, F), sizes)
        pi = np.arange(len(m)) - np.repeat(np.cumsum(sizes) - sizes, sizes)
        sel = np.nonzero(m >= 0)[0][::-1]          # a duplicate: its first point (last write)
        point[fi[sel], m[sel]] = pi[sel]
    step = np.zeros(F + 1, bool)                   # step[i]: frames i and i + 1 are neighbours
    step[:F - 1] = np.diff(frames) == 1
    added = 0
    for back in (True, False):
        todo = _candidates(point, step, first, back)
        span = range(F - 3, first - 1, -1) if back else range(first + 2, F)
        for i in span:
            if not todo[i]:
                continue
            j, k = (i + 1, i + 2) if back else (i - 1, i - 2)
            if not (step[min(i, j)] and step[min(j, k)]):
                continue                             # (a run reached a gap in the frames)
            run = (point[j] >= 0) & (point[k] >= 0)
            want = run & (point[i] < 0)
            glitch = run & (point[i] >= 0)
            if glitch.any():
                glitch &= _glitches(per_frame, point, frames, i, j, k, back, first, gate_m)
            want |= glitch
            if not want.any():
                continue
            # a glitch's points (with any merged duplicate) are released while the runs
            # choose, and given back where its run does not replace them
            held = {int(m): np.nonzero(marker_of[i] == m)[0] for m in np.nonzero(glitch)[0]}
            for idx in held.values():
                marker_of[i][idx] = -1
            free = np.nonzero(marker_of[i] < 0)[0]
            runs = np.nonzero(want)[0]
            got = _continuations(per_frame[j][point[j, runs]], per_frame[k][point[k, runs]],
                                 per_frame[i][free], gate_m, clear)
            for r in np.nonzero(got >= 0)[0]:
                p = free[got[r]]
                marker_of[i][p] = runs[r]
                point[i, runs[r]] = p
                added += 1
                nxt = i - 1 if back else i + 1      # the run goes on from here
                if first <= nxt < F:
                    todo[nxt] = True
            for m, idx in held.items():
                if got[np.searchsorted(runs, m)] >= 0:
                    continue                         # replaced by its run's point
                back_to = idx[marker_of[i][idx] < 0]  # what another run took stays taken
                marker_of[i][back_to] = m
                point[i, m] = back_to[0] if len(back_to) else -1
    return added


def _continuations(xj: np.ndarray, xk: np.ndarray, P: np.ndarray, gate_m: float,
                   clear: float) -> np.ndarray:
    """For runs at xj (the next frame) and xk (the one after), the index into P of the
    point that continues each (-1: none clearly does): nearest the linear extrapolation,
    within the gate, with no other point and no other run's extrapolation as near."""
    if not len(P):
        return np.full(len(xj), -1)
    pred = 2.0 * xj - xk                                              # (r, 3)
    d = np.linalg.norm(pred[:, None] - P[None], axis=2)               # (r, f)
    rows = np.arange(len(pred))
    near = d.argmin(1)
    d1 = d[rows, near]
    d[rows, near] = np.inf
    other_point = d.min(1) if d.shape[1] > 1 else np.full(len(pred), np.inf)
    d[rows, near] = d1
    other_run = np.full(len(pred), np.inf)
    if len(pred) > 1:
        col = d[:, near].copy()                                       # (r, r)
        np.fill_diagonal(col, np.inf)
        other_run = col.min(0)
    rival = np.maximum(clear * d1, gate_m)        # nothing else within the gate either
    take = (d1 < gate_m) & (other_point > rival) & (other_run > rival)
    return np.where(take, near, -1)


def _glitches(per_frame, point, frames, i, j, k, back, first, gate_m) -> np.ndarray:
    """Markers labelled in frame i on a point off their run's path (beyond the gate from
    the extrapolation of frames j and k) and not labelled on the far side of i: a label
    of one frame that the tracker took while re-finding the marker (the wrong point for
    a frame, the right one from the next). The run's continuation may replace it."""
    n = point.shape[1]
    lab = (point[i] >= 0) & (point[j] >= 0) & (point[k] >= 0)
    far = i - 1 if back else i + 1
    if first <= far < len(per_frame) and abs(int(frames[far]) - int(frames[i])) == 1:
        lab &= point[far] < 0
    out = np.zeros(n, bool)
    m = np.nonzero(lab)[0]
    if len(m):
        pred = 2.0 * per_frame[j][point[j, m]] - per_frame[k][point[k, m]]
        off = np.linalg.norm(per_frame[i][point[i, m]] - pred, axis=1) > gate_m
        out[m[off]] = True
    return out


def _candidates(point: np.ndarray, step: np.ndarray, first: int, back: bool) -> np.ndarray:
    """Frames where some marker's run, labelled in the two frames beyond, may go on: the
    marker unlabelled there, or labelled for that frame alone (a glitch). Frames the
    extension reaches later are added as it goes."""
    F = len(point)
    has = point >= 0
    todo = np.zeros(F, bool)
    if F < 3:
        return todo
    i = np.arange(F - 2) if back else np.arange(2, F)
    j, k = (i + 1, i + 2) if back else (i - 1, i - 2)
    far = i - 1 if back else i + 1
    linked = step[np.minimum(i, j)] & step[np.minimum(j, k)]
    far_ok = (far >= 0) & (far < F)
    far_has = np.zeros((len(i), point.shape[1]), bool)
    far_ok &= step[np.clip(np.minimum(i, far), 0, F)]
    far_has[far_ok] = has[far[far_ok]]
    open_ = ~has[i] | ~far_has
    todo[i] = linked & (has[j] & has[k] & open_).any(1)
    todo[:first] = False
    return todo
