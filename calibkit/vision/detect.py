"""Marker (blob) detection: bright or coloured spots in an image -> sub-pixel centroids.

This module is the detector's entry point (`detect`, `detect_reference`) and runs its
stages, one module each:

- detect_config: DetectorConfig (what counts as a marker) and Blobs (what was found);
- detect_threshold: the background level and noise, the threshold, the bright pixels,
  HSV colour filters;
- detect_regions: connected regions of the bright pixels, found without labelling the
  whole image (horizontal runs linked to the runs above, collapsed by pointer jumping);
- detect_centroids: the area filter, windowed background-subtracted centroids (every
  later stage inherits the centroid error, so the centroid is the point), roundness, the
  deblending of touching spots.

That numpy implementation is the reference (`detect_reference`); `detect` runs the same
steps as compiled kernels (calibkit.vision.detect_kernels, numba) where it can, with the
same results, in under 0.2 ms for a VGA frame with 40 markers (benchmarks/bench_detect.py).

Modes:
- "threshold": one threshold, fixed or automatic from the background level and noise.
- "multi": a falling series of thresholds; a region is kept at the lowest level at which it
  still holds a single intensity maximum and fits the size range, which separates touching
  or unevenly lit targets that one threshold would merge or lose.
- HSV ranges (colour images): each range is a filter of its own and `Blobs.label` says which
  range found the blob, so LEDs of different colours can mean different things.
"""

from __future__ import annotations

from collections.abc import Callable

import cv2
import numpy as np

from calibkit.core.errors import UserError
from calibkit.vision.detect_centroids import measure_regions
from calibkit.vision.detect_config import Blobs, DetectorConfig, HsvRange, jit_kernels
from calibkit.vision.detect_regions import Regions, Runs, label_pixels, label_pixels_with
from calibkit.vision.detect_threshold import (
    NO_MASK,
    auto_threshold,
    background_level,
    bright_pixels,
    estimate_background,
    hsv_inside,
)

__all__ = ["Blobs", "DetectorConfig", "HsvRange", "auto_threshold", "background_level",
           "detect", "detect_reference", "label_pixels"]


def detect(image: np.ndarray,
           config: DetectorConfig = DetectorConfig()) -> Blobs:  # noqa: B008 - frozen
    """Find the markers in one image: grayscale (h, w) or BGR colour (h, w, 3)."""
    return _detect(image, config, jit_kernels())


def detect_reference(image: np.ndarray,
                     config: DetectorConfig = DetectorConfig()) -> Blobs:  # noqa: B008 - frozen
    """`detect` in plain numpy, without the compiled kernels: the reference the tests hold
    the compiled path to (and the fallback where numba is unavailable)."""
    return _detect(image, config, None)


def _detect(image: np.ndarray, config: DetectorConfig, kernels) -> Blobs:
    image = np.asarray(image)
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    if image.ndim not in (2, 3) or (image.ndim == 3 and image.shape[2] not in (3, 4)):
        raise UserError(f"expected a grayscale or BGR image, got an array of shape "
                        f"{image.shape}")
    if image.shape[0] == 0 or image.shape[1] == 0:  # an empty crop: nothing to find
        return Blobs.empty()
    mask = config.mask
    if mask is not None and mask.shape != image.shape[:2]:
        raise UserError(f"the mask is {mask.shape[1]}x{mask.shape[0]} but the image is "
                        f"{image.shape[1]}x{image.shape[0]}; build the mask from this camera")
    if config.hsv_ranges:
        if image.ndim != 3:
            raise UserError("HSV ranges need a colour image; this one is grayscale")
        return _detect_hsv(image[:, :, :3], config, mask, kernels)
    if image.ndim == 3:
        code = cv2.COLOR_BGRA2GRAY if image.shape[2] == 4 else cv2.COLOR_BGR2GRAY
        image = cv2.cvtColor(image, code)
    maxima = None
    if kernels is not None and config.mode == "threshold" and image.dtype in (np.uint8,
                                                                              np.uint16):
        image = np.ascontiguousarray(image)
        maxima = kernels.chunk_maxima(image.reshape(-1))  # reads the frame into the cache
    if config.threshold == "auto":
        level, sigma = estimate_background(image, mask, kernels)
        threshold = level + max(config.auto_k * sigma, config.min_contrast)

        def background() -> tuple[float, float]:
            return level, sigma
    else:
        threshold = float(config.threshold)

        def background() -> tuple[float, float]:
            return estimate_background(image, mask, kernels)
    if maxima is not None:
        return _detect_compiled(kernels, image, maxima, threshold, config, mask, background)
    pix = bright_pixels(image, threshold, mask)
    if config.mode == "multi":
        return _detect_multi(image, pix, threshold, config, mask, background, kernels)
    regions = Runs.find(pix, image.shape[1]).regions(image)
    return measure_regions(image, regions, config, threshold, mask, background)


def _detect_compiled(kernels, image: np.ndarray, maxima: np.ndarray, threshold: float,
                     config: DetectorConfig, mask: np.ndarray | None,
                     background: Callable[[], tuple[float, float]]) -> Blobs:
    """The single-threshold mode with the compiled kernels: same blobs as the numpy path.
    `maxima`: the image's chunk maxima (kernels.chunk_maxima)."""
    if threshold >= np.iinfo(image.dtype).max:
        return Blobs.empty(threshold)
    tint = image.dtype.type(max(int(np.floor(threshold)), 0))  # v > t <=> v > floor(t)
    return _measure_compiled(kernels, image, tint, image, config, threshold, mask, background,
                             maxima=maxima)


def _measure_compiled(kernels, candidates: np.ndarray, tint, values: np.ndarray,
                      config: DetectorConfig, threshold: float, mask: np.ndarray | None,
                      background: Callable[[], tuple[float, float]],
                      label_value: int = 0, maxima: np.ndarray | None = None) -> Blobs:
    """Regions of the pixels of `candidates` above `tint` (not masked), measured on `values`
    (both contiguous): what Runs.find, Runs.regions and measure_regions do, compiled."""
    has_mask = mask is not None
    mask = np.ascontiguousarray(mask) if has_mask else NO_MASK
    if maxima is None:
        maxima = kernels.chunk_maxima(candidates.reshape(-1))
    hot = kernels.hot_chunks(maxima, tint)
    found = kernels.find_regions(candidates, tint, values, mask, has_mask, hot, 2048)
    if not found[-1]:  # more runs than the first guess: the bound for these hot chunks
        found = kernels.find_regions(candidates, tint, values, mask, has_mask, hot,
                                     kernels.max_runs(len(hot), values.shape[1]))
    runs, run_label, area, bbox, peak, _ = found
    if len(area) == 0:
        return Blobs.empty(threshold)
    level, sigma = background()
    uv, area, peak, bbox, roundness = kernels.measure(
        values, candidates, tint, mask, has_mask, runs, run_label, area, bbox, peak,
        float(config.min_area), float(config.max_area), float(config.min_roundness),
        int(config.window_margin_px), float(level), float(max(sigma, 0.5)))
    return Blobs(uv, area, peak, bbox, roundness, np.full(len(uv), label_value), threshold)


def _detect_hsv(bgr: np.ndarray, config: DetectorConfig, mask: np.ndarray | None,
                kernels) -> Blobs:
    """One pass per HSV range over the same image; brightness (V) weights the centroid."""
    if bgr.dtype != np.uint8:
        raise UserError(f"HSV detection needs an 8-bit colour image, got {bgr.dtype}")
    hsv = cv2.cvtColor(np.ascontiguousarray(bgr), cv2.COLOR_BGR2HSV)
    value = np.ascontiguousarray(hsv[:, :, 2])
    level, sigma = estimate_background(value, mask, kernels)

    def background() -> tuple[float, float]:
        return level, sigma
    parts = []
    for index, (lo, hi) in enumerate(config.hsv_ranges):
        inside = hsv_inside(hsv, lo, hi)
        if kernels is not None:
            parts.append(_measure_compiled(kernels, inside, np.uint8(0), value, config, level,
                                           mask, background, index))
            continue
        above = inside > 0
        if mask is not None:
            above &= ~mask
        pix = np.flatnonzero(above)
        regions = Runs.find(pix, bgr.shape[1]).regions(value)
        parts.append(measure_regions(value, regions, config, level, mask, background, index))
    out = Blobs.concatenate(parts)
    out.threshold = float("nan")
    return out


def _detect_multi(image: np.ndarray, base_pix: np.ndarray, threshold: float,
                  config: DetectorConfig, mask: np.ndarray | None,
                  background: Callable[[], tuple[float, float]], kernels) -> Blobs:
    """Falling thresholds; keep each maximum's largest region that is alone and in range.

    From the brightest level down, a region with no region of the level above inside it is
    a new maximum; a region holding two or more significant regions of the level above
    holds several maxima and is not a target. Each maximum keeps the region of the lowest
    level at which it was still alone and inside the size range, so touching spots are
    separated just above their saddle and isolated spots are measured at the base level.
    Regions smaller than the significance area (specks of noise on a spot's top) do not
    count as maxima of their own.
    """
    w = image.shape[1]
    if len(base_pix) == 0:
        return Blobs.empty(threshold)
    vals = image.reshape(-1)[base_pix].astype(np.float64)
    top = float(vals.max())
    levels = np.linspace(top, threshold, config.multi_levels + 1)[1:]
    levels = np.unique(np.floor(levels))[::-1]  # integer levels, falling, distinct
    significant_area = max(config.min_area, 3.0)
    prev_pix = prev_lab = prev_nmax = prev_id = prev_area = None
    next_id = 0
    # Per maximum id (at most one birth per pixel): the level and region it keeps so far.
    best_li = np.full(len(base_pix), -1, dtype=np.int64)
    best_r = np.full(len(base_pix), -1, dtype=np.int64)
    frozen = np.zeros(len(base_pix), dtype=bool)  # grew beyond max_area: stop updating
    per_level = []
    for li, t in enumerate(levels):
        sel = vals > t
        pix = base_pix[sel]
        lab, nreg = label_pixels_with(pix, w, kernels)
        per_level.append((pix, lab))
        area = np.bincount(lab, minlength=nreg)
        if prev_pix is None or len(prev_pix) == 0:
            nmax = np.ones(nreg, dtype=np.int64)
            ids = np.arange(next_id, next_id + nreg)
            next_id += nreg
        else:
            # Each region of the level above lies inside exactly one region of this level.
            first = np.zeros(len(prev_area), dtype=np.int64)
            first[prev_lab] = np.arange(len(prev_lab))
            parent = lab[np.searchsorted(pix, prev_pix[first])]
            signif = (prev_nmax > 1) | (prev_area >= significant_area)
            nmax = np.bincount(parent, weights=np.where(signif, prev_nmax, 0),
                               minlength=nreg).astype(np.int64)
            children = np.bincount(parent, minlength=nreg)
            ids = np.full(nreg, -1, dtype=np.int64)
            # A region whose only maximum comes from one child (or whose children are all
            # insignificant) inherits that child's id: the significant one, else the largest.
            order = np.lexsort((prev_area, signif, parent))
            last = np.flatnonzero(np.diff(parent[order], append=nreg) != 0)
            ids[parent[order[last]]] = prev_id[order[last]]
            newborn = children == 0
            ids[newborn] = np.arange(next_id, next_id + newborn.sum())
            next_id += int(newborn.sum())
            nmax = np.where(nmax == 0, 1, nmax)
            ids[nmax != 1] = -1
        alone = np.flatnonzero(nmax == 1)
        mids = ids[alone]
        live = ~frozen[mids]
        big = area[alone] > config.max_area
        frozen[mids[live & big]] = True
        grow = live & ~big & (area[alone] >= config.min_area)
        best_li[mids[grow]] = li
        best_r[mids[grow]] = alone[grow]
        prev_pix, prev_lab, prev_nmax, prev_id, prev_area = pix, lab, nmax, ids, area
    found = np.flatnonzero(best_li >= 0)
    if len(found) == 0:
        return Blobs.empty(threshold)
    # Gather the chosen regions (disjoint by construction) into one labelled pixel set,
    # one pass per level.
    pix_parts, lab_parts = [], []
    for li, (pix, lab) in enumerate(per_level):
        here = found[best_li[found] == li]
        if len(here) == 0:
            continue
        new_label = np.full(lab.max() + 1 if len(lab) else 0, -1, dtype=np.int64)
        new_label[best_r[here]] = np.searchsorted(found, here)
        got = new_label[lab]
        pix_parts.append(pix[got >= 0])
        lab_parts.append(got[got >= 0])
    pix = np.concatenate(pix_parts)
    labels = np.concatenate(lab_parts)
    regions = Regions.from_pixels(image, pix, labels, len(found))
    return measure_regions(image, regions, config, threshold, mask, background)
