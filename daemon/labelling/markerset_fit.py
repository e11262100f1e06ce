"""How well a marker set fits a take, checked before labelling it.

A set learned on one person labels another only as far as the bodies agree: a different
size is allowed for (the labeller scales the set and learns the take's own distances), a
segment of other proportions (longer legs) or a marker stuck elsewhere is where labels
go wrong, and a marker the take does not hold stays unlabelled. The check compares the
take's distances, labelled by its own labels or (for unlabelled points) by the start from
the marker set alone on a window of frames, with the set's: the body's scale, each
segment's length ratio to the set relative to that scale, each marker's placement
against its steadiest neighbours, the markers the take lacks, and a one-line verdict.
"""

from __future__ import annotations

import warnings
from dataclasses import asdict, dataclass

import numpy as np

from daemon.labelling.markerset import MarkerSet

SUBJECT_REL = 0.12        # the allowance for another subject the start from the set alone
PLACEMENT_M = 0.012       # makes (assign): 12 % of a distance and 12 mm, 1 SD
MISFIT = 1.0              # a marker this many allowances off its neighbours' distances
GOOD_MEDIAN = 0.5         # a good fit: the median marker within half an allowance ...
GOOD_WORST = 1.0          # ... and none beyond one
RIGID_SD_M = 0.008        # set pairs steadier than this should stay steady in the take
K_NEIGHBOURS = 6


@dataclass
class SegmentFit:
    name: str
    markers: int
    seen: int                  # markers of the segment seen in the take
    length_ratio: float        # the take's distances within the segment / the set's
    relative: float            # length_ratio / the body's scale (1: same proportions)
    misfit: float              # median distance error of its pairs, in allowances
    spread_mm: float           # how much its distances vary in the take
    set_spread_mm: float       # ... and in the set


@dataclass
class SetFit:
    labelled_by: str           # "labels" (the take's own) or "start" (from the set alone)
    frames: int                # frames compared
    scale: float               # the body's size against the set's (RMS distance ratio)
    misfit_median: float       # markers' misfit (see `misfit`): median and worst
    misfit_worst: float
    segments: list[SegmentFit]
    misfit: dict               # marker -> median error of its distances to its steadiest
    #                            neighbours, in allowances for another subject (1 SD)
    missing: list[str]         # markers of the set the take never shows
    extra: list[str]           # labels of the take the set does not have
    misplaced: list[str]       # markers whose misfit exceeds MISFIT, worst first
    bent: list[str]            # segments the set calls rigid that bend in the take
    verdict: str

    def to_json(self) -> dict:
        return asdict(self)


def check_fit(ms: MarkerSet, xyz: np.ndarray, labelled_by: str = "labels",
              extra: list[str] | None = None, noise_m: float = 0.003) -> SetFit:
    """Compare a labelled take (frames, n, 3) in the set's marker order (NaN: not
    seen) with the set."""
    xyz = np.asarray(xyz, float)
    n = ms.n
    d = np.linalg.norm(xyz[:, :, None] - xyz[:, None], axis=3)          # (F, n, n)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        D = np.nanmedian(d, axis=0)
        S = np.nanstd(d, axis=0)
    seen = np.isfinite(xyz).all(2).any(0)
    iu = np.triu_indices(n, 1)
    both = np.isfinite(D[iu]) & (ms.mean_m[iu] > 0)
    scale = float(np.sqrt(np.mean(D[iu][both] ** 2) / np.mean(ms.mean_m[iu][both] ** 2))) \
        if both.sum() >= 3 else float("nan")
    M = scale * ms.mean_m
    Z = np.abs(D - M) / np.sqrt((SUBJECT_REL * M) ** 2 + PLACEMENT_M ** 2 + ms.sd_m ** 2)
    segments, bent = [], []
    for sg in ms.segments:
        idx = np.array(sg.markers)
        if len(idx) < 2:
            continue
        a, b = np.triu_indices(len(idx), 1)
        i, j = idx[a], idx[b]
        ok = np.isfinite(D[i, j])
        ratio = float(D[i, j][ok].sum() / ms.mean_m[i, j][ok].sum()) if ok.any() else np.nan
        spread = float(np.sqrt(np.mean(S[i, j][ok] ** 2))) if ok.any() else np.nan
        z = float(np.median(Z[i, j][ok])) if ok.any() else np.nan
        segments.append(SegmentFit(sg.name, len(idx), int(seen[idx].sum()), _r(ratio, 4),
                                   _r(ratio / scale, 4), _r(z, 2), _r(1000 * spread, 1),
                                   _r(1000 * sg.spread_m, 1)))
        # a pair the set holds rigid that varies in the take: a wrong label, or not rigid
        rigid = ok & (ms.sd_m[i, j] < RIGID_SD_M)
        if rigid.any() and np.median(S[i, j][rigid]) > 3 * RIGID_SD_M + 2 * noise_m:
            bent.append(sg.name)
    sd = ms.sd_m.copy()
    np.fill_diagonal(sd, np.inf)
    order = np.argsort(sd, axis=1)
    misfit: dict[str, float] = {}
    med, count = _neighbour_median(np.take_along_axis(Z, order, axis=1), K_NEIGHBOURS)
    for m in np.nonzero(seen & (count >= 2))[0]:
        misfit[ms.labels[m]] = _r(float(med[m]), 2)
    worst_first = sorted(misfit, key=lambda k: -misfit[k])
    values = np.array(list(misfit.values())) if misfit else np.array([np.nan])
    fit = SetFit(labelled_by, int(len(xyz)), _r(scale, 4), _r(float(np.median(values)), 2),
                 _r(float(values.max()), 2), segments, misfit,
                 [ms.labels[m] for m in np.nonzero(~seen)[0]], list(extra or []),
                 [k for k in worst_first if misfit[k] > MISFIT], bent, "")
    fit.verdict = verdict(fit, n)
    return fit


def _neighbour_median(Z: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Per row of Z (n, m), steadiest neighbour first: the median of its first `k` finite
    values and how many there are (NaN where none), as np.median over each row's values
    would give (the mean of the middle two for an even count), for all rows at once."""
    fin = np.isfinite(Z)
    take = fin & (np.cumsum(fin, axis=1) <= k)
    v = np.sort(np.where(take, Z, np.inf), axis=1)[:, :k]
    c = take.sum(1)
    rows = np.arange(len(Z))
    lo = v[rows, np.maximum((c - 1) // 2, 0)]
    hi = v[rows, np.minimum(c // 2, k - 1)]
    med = np.where(c % 2 == 1, lo, (lo + hi) / 2.0)
    return np.where(c > 0, med, np.nan), c


def verdict(fit: SetFit, n: int) -> str:
    """One line: how the labelling will go with this set on this take, and why."""
    if not np.isfinite(fit.scale) or not fit.misfit:
        return "no fit: too few of the set's markers could be compared"
    notes = []
    if fit.missing:
        notes.append(f"the take lacks {len(fit.missing)} of {n} markers "
                     f"({_names(fit.missing)}: they stay unlabelled)")
    if fit.extra:
        notes.append(f"the set lacks {len(fit.extra)} of the take's labels "
                     f"({_names(fit.extra)})")
    if fit.bent:
        why = "the start from the set alone may be wrong there" if fit.labelled_by == \
            "start" else "wrong labels, or not rigid on this body"
        notes.append(f"segments the set holds rigid bend here ({_names(fit.bent)}: {why})")
    if fit.misplaced:
        notes.append(f"markers placed otherwise than in the set ({_names(fit.misplaced)})")
    size = "" if abs(fit.scale - 1) < 0.05 else f", body {fit.scale:.2f}x the set's size"
    if fit.misfit_median <= GOOD_MEDIAN and fit.misfit_worst <= GOOD_WORST and \
            not fit.bent and len(fit.missing) <= n // 8:
        level = "good fit"
        hint = "the start from the set alone should be right"
    elif len(fit.misplaced) + 3 * len(fit.bent) <= max(2, n // 8) and \
            len(fit.missing) <= n // 4:
        level = "fair fit"
        hint = "the start from the set alone should hold; check the markers named"
    else:
        level = "loose fit"
        hint = "a few labelled start frames (--start-labels) or a set learned on this " \
            "subject are safer"
    return f"{level}{size} (median marker {fit.misfit_median:.2f}, worst " \
        f"{fit.misfit_worst:.2f} allowances): " + "; ".join(notes + [hint])


def _r(x: float, digits: int) -> float:
    return round(x, digits) if np.isfinite(x) else x


def _names(names: list[str], most: int = 4) -> str:
    more = f" and {len(names) - most} more" if len(names) > most else ""
    return ", ".join(names[:most]) + more


def check_points(ms: MarkerSet, per_frame: list[np.ndarray], noise_m: float = 0.003
                 ) -> SetFit:
    """The fit on unlabelled points: a window of frames labelled from the set alone
    (daemon/labelling/start.py) compared with the set."""
    # deferred on purpose: loads SciPy's optimisers, SciPy's sparse graphs... only where used
    from daemon.labelling.start import window_start

    _, _, xyz = window_start(per_frame, ms, noise_m=noise_m)
    return check_fit(ms, xyz, "start", noise_m=noise_m)
