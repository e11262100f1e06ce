"""Fitting a rigid body's definition to the markers of a take, and saying why a body is not found.

Why: a definition made on another day, or exported by another tool, need not match the
markers of the take: a marker knocked a few millimetres, a definition Motive refined
internally but exported unrefined. Identification compares inter-marker distances at a
few millimetres' tolerance, so such a body is never found, or found on the markers that
still agree and then posed with a template that pulls it off the truth. Motive's answer
is to refine the body on the data; this is that, on a file:

1. Frames where the body's markers are present (all, or all but one of five or more)
   are found with a looser tolerance (LOOSE_FACTOR x the distance tolerance), scanning the
   take from its start in even steps (the first confident frames found).
2. Only frames whose inter-marker distances agree with the median of those frames count
   (CONSISTENT_M): a stray point taken for a marker, or another body, does not.
3. The real geometry is their average in the body frame (generalised Procrustes: fit,
   bring every frame's points into the body frame, take the median, repeat).
4. It is put into the definition's own body frame by a fit on the markers that agree with
   the definition (AGREE_M, at least three: the worst is dropped until the rest agree), so
   the pivot and axes, and so the reported pose, stay the definition's. With fewer than
   three agreeing nothing is learned: these may not be its markers (a three-marker body
   cannot say which of its markers is off, so one with a marker off is not learned; the
   hint then names the tolerance that finds it).

The learned template replaces the definition when a marker sits more than REFINE_ABOVE x
the distance tolerance from where the definition puts it (2 mm at the default 4 mm).
In `auto` a cheap first look comes before all that: a definition found as it is, every
marker, in the first MIN_FRAMES frames scanned, each marker within AGREES_M of the fit, is
kept without the loose search (which costs about 0.2 s of CPU a body, and changes nothing
for a definition that fits: 2.3 of 4.0 s on a 10-body take where all fitted).
When a body is still not found, closest_fit says how far its distances were from the
best candidate points, for the message that tells the user what to change.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, replace

import numpy as np

from daemon.tracking.rigid import BodyDef, find_body, kabsch_batch

LOOSE_FACTOR = 3.0  # the learning search's distance tolerance, times the tracking one
LOOSE_MIN_M = 0.010  # ... and at least this
CONSISTENT_M = 0.0025  # a frame's distances within this of the frames' median ones
AGREE_M = 0.0015  # a learned marker within this of the definition's agrees with it
REFINE_ABOVE = 0.5  # replace the definition when a marker is off by more than this times
# the distance tolerance: nearer, the definition still identifies the body and poses it
# within about a tenth of that; farther, noise makes identification fail or pull the pose
MIN_FRAMES = 10  # consistent frames needed to learn from
WANT_FRAMES = 60  # frames learned from (the first ones found)
SCAN_FRAMES = 300  # frames looked at, at most, evenly spaced from the start
HINT_TOL_M = 0.025  # how far off the closest-fit search looks for a body's distances
HINT_FRAMES = 60  # frames it looks at (a loose search per frame is slow: a hint only)
# auto's first look: a marker this far from the definition's fit at most (a marker off by
# REFINE_ABOVE x tol shows about 3/4 of that after a fit that spreads it over four markers)
AGREES_M = 0.001


@dataclass(eq=False)
class BodyRefit:
    """What the take says about one body's definition."""

    name: str
    frames_used: int  # consistent frames the geometry was learned from (0: not learned)
    markers_m: np.ndarray | None  # (K, 3) learned template in the definition's frame
    shift_m: np.ndarray | None  # (K,) each learned marker's distance from the definition's
    agree: np.ndarray | None  # (K,) markers the frame alignment used
    applied: bool = False

    def summary(self) -> dict:
        """For the figures' JSON: how the definition was changed, in millimetres."""
        out = {"frames_used": self.frames_used, "applied": self.applied}
        if self.shift_m is not None:
            out["marker_shift_mm"] = [round(float(s) * 1000.0, 3) for s in self.shift_m]
        return out


def _frames_to_scan(n_frames: int, most: int = SCAN_FRAMES) -> np.ndarray:
    """At most `most` frame rows, evenly spaced from the first."""
    return np.arange(0, n_frames, max(1, -(-n_frames // most)))


def _points(xyz_frame: np.ndarray) -> np.ndarray:
    return xyz_frame[np.isfinite(xyz_frame).all(axis=1)]


def _matches(xyz: np.ndarray, body: BodyDef, tol_m: float, need: int, want: int):
    """(frames, points (M, K, 3) NaN where a marker was skipped) of the first `want` scanned
    frames where find_body places at least `need` of the body's markers at tol_m."""
    probe = replace(body, min_markers_start=need)
    frames, found = [], []
    for f in _frames_to_scan(len(xyz)):  # find_body is a search per frame, not per point
        pts = _points(xyz[f])
        if len(pts) < need:
            continue
        match = find_body(probe, pts, tol_m, tol_m)
        if match is None:
            continue
        got = np.full((len(body.markers), 3), np.nan)
        got[match >= 0] = pts[match[match >= 0]]
        frames.append(int(f))
        found.append(got)
        if len(found) >= want:
            break
    return np.array(frames, dtype=np.int64), np.array(found).reshape(-1, len(body.markers), 3)


def _distances(P: np.ndarray) -> np.ndarray:
    return np.linalg.norm(P[:, :, None, :] - P[:, None, :, :], axis=3)


def _procrustes(P: np.ndarray, start: np.ndarray, rounds: int = 5) -> np.ndarray:
    """The template (K, 3) that frames of points P (F, K, 3), NaN where a marker was not
    found, are rigid copies of, starting from `start`: each round fits every frame to it
    on its found markers and takes each marker's median in the body frame. A marker found
    in fewer than MIN_FRAMES frames keeps its place in `start`."""
    template = start.copy()
    seen = np.isfinite(P).all(axis=2)
    w = seen.astype(np.float64)
    learnt = seen.sum(axis=0) >= MIN_FRAMES
    Q = np.where(seen[..., None], P, 0.0)
    for _ in range(rounds):
        R, t = kabsch_batch(np.broadcast_to(template, P.shape), Q, w)
        local = np.einsum("fji,fkj->fki", R, Q - t[:, None, :])
        local[~seen] = np.nan
        template = np.where(learnt[:, None], np.nanmedian(
            np.where(learnt[None, :, None], local, 0.0), axis=0), start)
    return template


def _align(learned: np.ndarray, definition: np.ndarray):
    """(learned moved into the definition's frame, markers the fit used): a rigid fit on
    the markers that agree within AGREE_M, the worst dropped while more than three remain."""
    use = np.ones(len(definition), bool)
    while True:
        R, t = kabsch_batch(learned[None], definition[None], use[None].astype(np.float64))
        moved = learned @ R[0].T + t[0]
        e = np.linalg.norm(moved - definition, axis=1)
        if e[use].max() <= AGREE_M or use.sum() <= 3:
            return moved, use
        use[np.argmax(np.where(use, e, -1.0))] = False


def learn_geometry(xyz: np.ndarray, body: BodyDef, tol_m: float) -> BodyRefit:
    """The body's real geometry from a take's anonymous markers xyz (F, P, 3), NaN-padded
    (see the module docstring); frames_used 0 when too few frames were found to learn it."""
    k = len(body.markers)
    loose = max(LOOSE_FACTOR * tol_m, LOOSE_MIN_M)
    need = min(k, max(4, k - 1))  # four points fix a body; one of five may be hidden
    _, P = _matches(xyz, body, loose, need, WANT_FRAMES)
    none = BodyRefit(body.name, 0, None, None, None)
    if len(P) < MIN_FRAMES:
        return none
    D = _distances(P)  # NaN for pairs with a marker not found
    with warnings.catch_warnings():  # a pair never found together has no median: NaN
        warnings.simplefilter("ignore", RuntimeWarning)
        off = np.abs(D - np.nanmedian(D, axis=0))
    consistent = np.nanmax(np.where(np.isfinite(off), off, 0.0), axis=(1, 2)) <= CONSISTENT_M
    if consistent.sum() < MIN_FRAMES:
        return none
    learned = _procrustes(P[consistent], body.markers)
    moved, use = _align(learned, body.markers)
    if np.linalg.norm(moved - body.markers, axis=1)[use].max() > AGREE_M:
        return none  # fewer than three markers agree: not this body's markers
    shift = np.linalg.norm(moved - body.markers, axis=1)
    return BodyRefit(body.name, int(consistent.sum()), moved, shift, use)


def definition_fits(xyz: np.ndarray, body: BodyDef, tol_m: float) -> bool:
    """Whether the definition, as it is, finds the body with every marker in MIN_FRAMES of
    the first frames scanned, each marker within AGREES_M of the fitted definition (median
    over those frames): then there is nothing to learn."""
    k = len(body.markers)
    _, P = _matches(xyz, body, tol_m, k, MIN_FRAMES)
    if len(P) < MIN_FRAMES or np.isnan(P).any():
        return False
    src = np.broadcast_to(body.markers, P.shape)
    R, t = kabsch_batch(src, P, np.ones(P.shape[:2]))
    fitted = np.einsum("bij,bkj->bki", R, src) + t[:, None, :]
    return float(np.median(np.linalg.norm(P - fitted, axis=2), axis=0).max()) <= AGREES_M


def refine_bodies(xyz: np.ndarray, bodies: list[BodyDef], tol_m: float,
                  mode: str = "auto") -> tuple[list[BodyDef], list[BodyRefit]]:
    """The definitions to track with, and what was learned about each. mode 'off' keeps
    every definition; 'auto' replaces one whose learned geometry has a marker more than
    REFINE_ABOVE x tol_m from the definition's; 'on' replaces every one that was learned."""
    if mode not in ("auto", "on", "off"):
        raise ValueError(f"refine mode {mode!r}")
    out, refits = [], []
    for body in bodies:
        if mode == "off":
            out.append(body)
            refits.append(BodyRefit(body.name, 0, None, None, None))
            continue
        if mode == "auto" and definition_fits(xyz, body, tol_m):
            out.append(body)
            refits.append(BodyRefit(body.name, 0, None, None, None))
            continue
        refit = learn_geometry(xyz, body, tol_m)
        if refit.frames_used and (mode == "on" or refit.shift_m.max() > REFINE_ABOVE * tol_m):
            refit.applied = True
            body = replace(body, markers=refit.markers_m.copy())
        out.append(body)
        refits.append(refit)
    return out, refits


@dataclass(frozen=True)
class ClosestFit:
    """The best candidate for a body in the frames looked at: `residual_m` is the largest
    difference between a pair of its markers' distances and the points' (None: no points
    within HINT_TOL_M), in frame index `frame` (of the take's rows), with `markers` found."""

    residual_m: float | None
    frame: int = -1
    markers: int = 0


def closest_fit(xyz: np.ndarray, body: BodyDef) -> ClosestFit:
    """How near the take comes to holding the body: over the scanned frames, the candidate
    points (at least min_markers_start of its markers, within HINT_TOL_M) whose distances
    differ least from the definition's."""
    k = len(body.markers)
    need = max(3, min(body.min_markers_start, k))
    probe = replace(body, min_markers_start=need)
    best = ClosestFit(None)
    for f in _frames_to_scan(len(xyz), HINT_FRAMES):
        pts = _points(xyz[f])
        if len(pts) < need:
            continue
        match = find_body(probe, pts, HINT_TOL_M, HINT_TOL_M)
        if match is None:
            continue
        sel = np.flatnonzero(match >= 0)
        got = pts[match[sel]]
        d = np.linalg.norm(got[:, None] - got[None], axis=2)
        r = float(np.abs(d - body.distances[np.ix_(sel, sel)]).max())
        if best.residual_m is None or (len(sel), -r) > (best.markers, -best.residual_m):
            best = ClosestFit(r, int(f), len(sel))
    return best


def hint(body: BodyDef, fit: ClosestFit, tol_m: float, refit: BodyRefit | None,
         posed_fraction: float) -> str:
    """One line for a body posed in (almost) no frame: the closest fit and what to change."""
    seen = (f"posed in {100 * posed_fraction:.1f}% of frames" if posed_fraction > 0
            else "never found")
    if fit.residual_m is None:
        need = max(3, min(body.min_markers_start, len(body.markers)))
        return (f"body {body.name!r} {seen}: no {need} points in any frame match its "
                f"distances within {HINT_TOL_M * 1000:.0f} mm; "
                "is it in this take, and are its markers those of the definition?")
    r_mm = fit.residual_m * 1000.0
    tol_mm = tol_m * 1000.0
    advice = []
    if r_mm >= tol_mm:
        advice.append(f"--distance-tol-mm {int(np.ceil(r_mm + 1.0))}")
    if refit is None or not refit.applied:
        advice.append("--refine-bodies on")
    todo = (" or ".join(advice) if advice else
            "check that the body's markers stay in view of the cameras")
    return (f"body {body.name!r} {seen}: closest fit in frame row {fit.frame}, "
            f"{fit.markers} markers, distances off by up to {r_mm:.1f} mm (tolerance "
            f"{tol_mm:g} mm); try {todo}")
