"""How the wand's length error varies where a solve cannot hide it: across the volume, from
the image centre to its edges, in held-out regions, and as a trend with position.

Why: wrong intrinsics warp the reconstructed space while the pixels still fit, and a rigid
wand's length then depends on where it is. Each figure here is that dependence less what the
per-frame noise alone would give, so a figure above zero is structure, not scatter.

Every figure is computed only where the capture holds the data for it (a real capture of
30-100 frames fills few cells of the volume and may hold nothing out); otherwise it is NaN
and `<figure>_reason` says why in words a user can act on.
"""

from __future__ import annotations

import numpy as np

VOLUME_CELLS = (3, 3, 2)  # x, y, z quantile bins of the wand's centre, on a large capture
# coarser grids tried in turn on a smaller one, until two cells hold MIN_CELL_FRAMES each
COARSER_CELLS = ((2, 2, 2), (2, 2, 1), (2, 1, 1))
MIN_CELL_FRAMES = 10
MIN_RADIUS_FRAMES = 9  # three per third, the least that gives each third a spread
TREND_TERMS = 4  # the trend's regressors: the wand centre's x, y, z and its image radius
MIN_TREND_FRAMES = 15  # 3 frames per fitted coefficient (4 terms and the mean)


def systematics(figures: list[dict], region: dict | None, wand_length_m: float,
                holdout_share: float | None = None) -> dict:
    """The length error's structure over the frames of all `figures` (wand_report.evaluate
    results, e.g. solved and held out), each figure beside its own noise, in mm and in %
    of the wand's length (scale-free, so it means the same for a wand of unknown length):

    volume: the spread of the mean length error over cells of the volume (quantile bins of
    the wand's centre, VOLUME_CELLS or coarser on a small capture, cells with
    MIN_CELL_FRAMES or more): the RMS of the cell means about the overall mean, less what
    the per-frame noise alone gives (sqrt(max(0, ms - noise^2))).
    radius: the mean length error of the third of frames seen farthest from the image
    centres minus that of the nearest third, less two standard errors (at least 0).
    region: the mean length error in the held-out regions minus that over the other frames,
    less two standard errors.
    trend: the part of the length error a linear function of the wand's position (x, y, z)
    and image radius explains, less what noise alone would explain (the regression's
    sum of squares less TREND_TERMS residual variances, per frame): a warp that bends the
    space smoothly shows here on as few as MIN_TREND_FRAMES frames.
    """
    err = np.concatenate([f["frame_length_error_mm"] for f in figures])
    centre = np.concatenate([f["frame_centre_m"] for f in figures]).reshape(-1, 3)
    radius = np.concatenate([f["frame_radius"] for f in figures])
    ok = np.isfinite(err) & np.isfinite(centre).all(axis=1) & np.isfinite(radius)
    err, centre, radius = err[ok], centre[ok], radius[ok]
    length_mm = 1000.0 * wand_length_m
    out: dict = {"frames": int(len(err))}
    if not length_mm > 0:
        for key in ("volume", "radius", "region", "trend"):
            out[f"{key}_mm"] = out[f"{key}_pct"] = float("nan")
            out[f"{key}_reason"] = "a 1-marker wand has no length"
        out["radius_trend_mm"] = out["region_bias_mm"] = float("nan")
        return out
    out.update(_volume(err, centre))
    out.update(_radius(err, radius))
    out.update(_region(err, region, holdout_share))
    out.update(_trend(err, centre, radius))
    for k in ("volume", "radius", "region", "trend"):
        out[f"{k}_pct"] = 100.0 * out[f"{k}_mm"] / length_mm
    return out


def _cells(centre: np.ndarray, bins: tuple[int, int, int]) -> np.ndarray:
    key = np.zeros(len(centre), dtype=np.int64)
    for axis, n in enumerate(bins):
        edges = np.quantile(centre[:, axis], np.arange(1, n) / n)
        key = key * n + np.searchsorted(edges, centre[:, axis])
    return np.unique(key, return_inverse=True)[1]


def _volume(err: np.ndarray, centre: np.ndarray) -> dict:
    for bins in (VOLUME_CELLS, *COARSER_CELLS):
        cell = _cells(centre, bins) if len(err) else np.zeros(0, dtype=np.int64)
        n = np.bincount(cell)
        use = n >= MIN_CELL_FRAMES
        if use.sum() >= 2:
            break
    else:
        return {"volume_mm": float("nan"), "volume_cells": 0,
                "volume_reason": f"{len(err)} frames with both wand ends reconstructed fill "
                                 f"fewer than two cells of the volume with {MIN_CELL_FRAMES} "
                                 "frames each: capture more frames, spread through the volume"}
    keep = use[cell]
    e, c, n = err[keep], cell[keep], n
    mean = np.bincount(c, e, len(n))[use] / n[use]
    var = np.bincount(c, e**2, len(n))[use] / n[use] - mean**2
    ms = np.average((mean - e.mean()) ** 2, weights=n[use])
    noise2 = np.average(var / np.maximum(n[use] - 1, 1), weights=n[use])
    return {"volume_mm": float(np.sqrt(max(0.0, ms - noise2))), "volume_cells": int(use.sum()),
            "volume_grid": list(bins)}


def _radius(err: np.ndarray, radius: np.ndarray) -> dict:
    if len(err) < MIN_RADIUS_FRAMES:
        return {"radius_mm": float("nan"), "radius_trend_mm": float("nan"),
                "radius_reason": f"{len(err)} frames with both wand ends reconstructed (it "
                                 f"takes {MIN_RADIUS_FRAMES})"}
    lo, hi = np.quantile(radius, [1 / 3, 2 / 3])
    inner, outer = err[radius <= lo], err[radius >= hi]
    if len(inner) < 2 or len(outer) < 2 or not hi > lo:
        return {"radius_mm": float("nan"), "radius_trend_mm": float("nan"),
                "radius_reason": "the wand was seen at the same distance from the image "
                                 "centres throughout"}
    trend = outer.mean() - inner.mean()
    se = np.sqrt(inner.var(ddof=1) / len(inner) + outer.var(ddof=1) / len(outer))
    return {"radius_mm": float(max(0.0, abs(trend) - 2 * se)), "radius_trend_mm": float(trend)}


def _region(err: np.ndarray, region: dict | None, holdout_share: float | None) -> dict:
    nan = {"region_mm": float("nan"), "region_bias_mm": float("nan")}
    if holdout_share is not None and holdout_share <= 0:
        return {**nan, "region_reason": "no frames held out (--holdout 0)"}
    inside = np.zeros(0) if region is None else region["frame_length_error_mm"]
    inside = inside[np.isfinite(inside)]
    if len(inside) < MIN_CELL_FRAMES or len(err) <= len(inside):
        return {**nan, "region_reason": "no whole region of the volume was held out (it "
                                        "takes a capture of a few hundred frames to hold "
                                        "whole cells out and still solve)"}
    bias = inside.mean() - err.mean()
    se = np.sqrt(inside.var(ddof=1) / len(inside) + err.var(ddof=1) / len(err))
    return {"region_mm": float(max(0.0, abs(bias) - 2 * se)), "region_bias_mm": float(bias)}


def _trend(err: np.ndarray, centre: np.ndarray, radius: np.ndarray) -> dict:
    n = len(err)
    if n < MIN_TREND_FRAMES:
        return {"trend_mm": float("nan"),
                "trend_reason": f"{n} frames with both wand ends reconstructed (it takes "
                                f"{MIN_TREND_FRAMES})"}
    X = np.column_stack([centre, radius])
    X = X - X.mean(axis=0)
    spread = X.std(axis=0)
    X = X[:, spread > 1e-12 * max(1.0, float(spread.max()))]
    e = err - err.mean()
    coef, *_ = np.linalg.lstsq(X, e, rcond=None)
    fitted = X @ coef
    dof = n - X.shape[1] - 1
    s2 = float(np.sum((e - fitted) ** 2)) / dof
    explained = (float(np.sum(fitted**2)) - X.shape[1] * s2) / n
    return {"trend_mm": float(np.sqrt(max(0.0, explained)))}
