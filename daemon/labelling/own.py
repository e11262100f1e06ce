"""The body's own distances, from labelled start frames, judging labels the set proposes.

Evidence about a take's labels ranks: labelled start frames first (a person checked
them), then the distances the take's tracks keep, then the marker set (learned on other
subjects). Verification compares windows with the set, and a body built otherwise than
the set's (a longer shank, a wider pelvis, markers stuck elsewhere) looks wrong to it:
the set's search then "repairs" right labels toward the set. With labelled start frames
this body's distances are known, and a new label the set proposes must agree with them.
"""

from __future__ import annotations

import numpy as np

from daemon.labelling.assign import pair_stats

OWN_MISFIT = 3.0      # a track taking a marker: within 3 tolerances of the start's distances
OWN_WORSE = 0.5       # a labelled track renamed may fit them at most this much worse


def own_agrees(X: np.ndarray, lab: np.ndarray, cur: np.ndarray, own: tuple | None,
                spread: np.ndarray, noise_m: float) -> bool:
    """Whether new labels `lab` of tracks X agree with the body's own distances `own`
    (from labelled start frames; `spread` the set's SD of each pair, how a body moves
    it): a labelled track whose marker fits them (OWN_MISFIT) and is renamed must fit
    them about as well under its new marker (OWN_WORSE: an extra marker on the head took
    LBHD's name and LBHD's track RBHD's, which the set scored higher), and an unlabelled
    track given a marker must sit where they put it. A label that does not fit them
    they do not vouch for, and pairs the start never saw cannot tell: the set decides."""
    if own is None:
        return True
    moved = np.nonzero((lab >= 0) & (lab != cur))[0]
    if not len(moved):
        return True
    D, _ = pair_stats(X)
    new = own_misfit(D, lab, moved, own, spread, noise_m)
    was = own_misfit(D, cur, moved, own, spread, noise_m)
    held = np.isfinite(was)
    vouched = held & (was <= OWN_MISFIT)        # they vouch only for a label that fits
    bad = np.isfinite(new) & np.where(held, vouched & (new > was + OWN_WORSE),
                                      new > OWN_MISFIT)
    return not bad.any()


def own_misfit(D: np.ndarray, lab: np.ndarray, tracks: np.ndarray, own: tuple,
                spread: np.ndarray, noise_m: float, k: int = 6) -> np.ndarray:
    """Per track of `tracks` (labelled `lab`), the median error of its distances to the
    other labelled tracks against the body's own (`own`: mean, SD (n, n)), over its `k`
    steadiest pairs by the set's `spread` (a few start frames cannot tell which pairs
    a body moves), in units of their tolerance; NaN where it has no such pair
    (or no label)."""
    M, S = own
    others = np.nonzero(lab >= 0)[0]
    out = np.full(len(tracks), np.nan)
    ok_t = lab[tracks] >= 0
    if not ok_t.any() or len(others) < 2:
        return out
    t = tracks[ok_t]
    m = M[np.ix_(lab[t], lab[others])]
    sd = spread[np.ix_(lab[t], lab[others])]
    d = D[np.ix_(t, others)]
    tol = np.sqrt(sd ** 2 + S[np.ix_(lab[t], lab[others])] ** 2) + 2.0 * noise_m + 0.004
    e = np.abs(d - m) / tol
    e[t[:, None] == others[None]] = np.nan
    key = np.where(np.isfinite(e), sd, np.inf)
    first = np.argsort(key, axis=1)[:, :k]
    pick = np.take_along_axis(e, first, axis=1)
    with np.errstate(all="ignore"):
        med = np.nanmedian(np.where(np.isfinite(pick), pick, np.nan), axis=1) \
            if np.isfinite(pick).any() else np.full(len(t), np.nan)
    out[ok_t] = med
    return out
