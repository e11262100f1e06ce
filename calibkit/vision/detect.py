"""Marker (blob) detection: bright or coloured spots in an image -> sub-pixel centroids.

Every later stage (calibration, triangulation, tracking) inherits the centroid error, so the
centroid is the point: it is the intensity-weighted mean position with the local background
subtracted, taken over a window a little larger than the thresholded region. Weighting only
the pixels above the threshold would cut off the spot's skirt unevenly whenever the spot is
not centred on a pixel, and bias the centroid towards the pixel grid ("pixel locking").

Regions are found without labelling the whole image (OpenCV's labeller with statistics costs
milliseconds per VGA frame): the pixels above the threshold are gathered once, joined into
horizontal runs, the runs are linked to overlapping runs in the row above (8-connectivity),
and the run forest is collapsed by pointer jumping. All per-blob sums are `np.bincount`s over
gathered window pixels, so there is no Python loop per blob. That numpy implementation is
the reference (`detect_reference`); `detect` runs the same steps as compiled kernels
(calibkit.vision.detect_kernels, numba) where it can, with the same results, in under 0.2 ms for a
VGA frame with 40 markers (benchmarks/bench_detect.py).

Modes:
- "threshold": one threshold, fixed or automatic from the background level and noise.
- "multi": a falling series of thresholds; a region is kept at the lowest level at which it
  still holds a single intensity maximum and fits the size range, which separates touching
  or unevenly lit targets that one threshold would merge or lose.
- HSV ranges (colour images): each range is a filter of its own and `Blobs.label` says which
  range found the blob, so LEDs of different colours can mean different things.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass, field

import cv2
import numpy as np

from calibkit.core.errors import UserError

HsvRange = tuple[tuple[int, int, int], tuple[int, int, int]]


@dataclass(eq=False)
class Blobs:
    """Blobs of one image, one row per blob (columnar, like Observations).

    uv: (N, 2) float64 centroids in pixels, pixel centres at integer coordinates.
    area: pixels above the threshold; peak: brightest pixel value (of the weighting image);
    bbox: (N, 4) int32 x0, y0, x1, y1 inclusive, of the thresholded region; roundness:
    minor/major axis ratio from the second moments (1 = round, 0 = a line); label: the index
    of the HSV range that found the blob (0 for grayscale). `threshold` is the level used.
    """

    uv: np.ndarray
    area: np.ndarray
    peak: np.ndarray
    bbox: np.ndarray
    roundness: np.ndarray
    label: np.ndarray
    threshold: float = float("nan")

    def __post_init__(self) -> None:
        n = len(self.uv)
        self.uv = np.asarray(self.uv, dtype=np.float64).reshape(n, 2)
        self.area = np.asarray(self.area, dtype=np.float32).reshape(n)
        self.peak = np.asarray(self.peak, dtype=np.float32).reshape(n)
        self.bbox = np.asarray(self.bbox, dtype=np.int32).reshape(n, 4)
        self.roundness = np.asarray(self.roundness, dtype=np.float32).reshape(n)
        self.label = np.asarray(self.label, dtype=np.int32).reshape(n)

    def __len__(self) -> int:
        return len(self.uv)

    @classmethod
    def empty(cls, threshold: float = float("nan")) -> Blobs:
        z = np.zeros(0)
        return cls(np.zeros((0, 2)), z, z, np.zeros((0, 4)), z, z, threshold)

    def select(self, mask) -> Blobs:
        """The blobs where `mask` (bool or index array) holds."""
        return Blobs(self.uv[mask], self.area[mask], self.peak[mask], self.bbox[mask],
                     self.roundness[mask], self.label[mask], self.threshold)

    @staticmethod
    def concatenate(parts: list[Blobs]) -> Blobs:
        if not parts:
            return Blobs.empty()
        cat = np.concatenate
        return Blobs(cat([p.uv for p in parts]), cat([p.area for p in parts]),
                     cat([p.peak for p in parts]), cat([p.bbox for p in parts]),
                     cat([p.roundness for p in parts]), cat([p.label for p in parts]),
                     parts[0].threshold)

    def to_records(self) -> list[dict]:
        """One dict per blob, the JSON layout of `calibkit detect --json`."""
        return [{"u": float(u), "v": float(v), "area": float(a), "peak": float(p),
                 "roundness": round(float(r), 4), "bbox": [int(b) for b in box],
                 "label": int(lab)}
                for (u, v), a, p, r, box, lab in zip(self.uv, self.area, self.peak,
                                                     self.roundness, self.bbox, self.label,
                                                     strict=True)]


@dataclass(frozen=True)
class DetectorConfig:
    """What counts as a marker.

    threshold: a pixel value (pixels brighter than it are candidates) or "auto": the
    background level plus max(auto_k * noise sigma, min_contrast), both measured on the
    image. min_area/max_area: the size range in pixels above the threshold (rejects noise
    specks and large reflections). min_roundness: minor/major axis ratio (rejects
    line-shaped glints). mode: "threshold" or "multi" (falling series of `multi_levels`
    thresholds from the brightest pixel down to the threshold). hsv_ranges: for colour
    (BGR) images, ((h, s, v) low, (h, s, v) high) ranges in OpenCV's HSV (h 0..179); a low
    h above the high h wraps around red. mask: bool (h, w), True where pixels are ignored.
    window_margin_px: how far beyond the thresholded region the centroid window reaches.
    """

    threshold: float | str = "auto"
    min_area: float = 2.0
    max_area: float = 4000.0
    min_roundness: float = 0.0
    mode: str = "threshold"
    hsv_ranges: tuple[HsvRange, ...] = ()
    mask: np.ndarray | None = field(default=None, compare=False)
    auto_k: float = 6.0
    min_contrast: float = 8.0
    window_margin_px: int = 2
    multi_levels: int = 12

    def __post_init__(self) -> None:
        t = self.threshold
        if isinstance(t, str):
            if t != "auto":
                raise UserError(f"threshold must be a number or 'auto', got {t!r}")
        elif not np.isfinite(t) or t < 0:
            raise UserError(f"threshold must be a non-negative number or 'auto', got {t}")
        if self.min_area < 0 or self.max_area < self.min_area:
            raise UserError(f"area range must satisfy 0 <= min_area <= max_area, got "
                            f"{self.min_area}..{self.max_area}")
        if not 0.0 <= self.min_roundness <= 1.0:
            raise UserError(f"min_roundness must be in 0..1, got {self.min_roundness}")
        if self.mode not in ("threshold", "multi"):
            raise UserError(f"mode must be 'threshold' or 'multi', got {self.mode!r}")
        if self.window_margin_px < 0 or self.multi_levels < 2:
            raise UserError("window_margin_px must be >= 0 and multi_levels >= 2")
        ranges = tuple((tuple(int(c) for c in lo), tuple(int(c) for c in hi))
                       for lo, hi in self.hsv_ranges)
        for lo, hi in ranges:
            if len(lo) != 3 or len(hi) != 3:
                raise UserError(f"an HSV range needs 3 values per end, got {lo}:{hi}")
            if not (0 <= lo[0] <= 179 and 0 <= hi[0] <= 179) or not all(
                    0 <= c <= 255 for c in (*lo[1:], *hi[1:])):
                raise UserError(f"HSV range {lo}:{hi} is outside OpenCV's H 0..179, "
                                "S and V 0..255")
            if lo[1] > hi[1] or lo[2] > hi[2]:
                raise UserError(f"HSV range {lo}:{hi} has a low S or V above the high one")
        object.__setattr__(self, "hsv_ranges", ranges)
        if self.mask is not None:
            object.__setattr__(self, "mask", np.asarray(self.mask, dtype=bool))

    def replace(self, **changes) -> DetectorConfig:
        from dataclasses import replace
        return replace(self, **changes)


_kernels_module = None


def _kernels():
    """calibkit.vision.detect_kernels (numba, imported on first use: it costs ~0.5 s), or None
    where numba is missing or CALIBKIT_NO_JIT is set: detection then runs in numpy."""
    global _kernels_module
    if _kernels_module is None:
        import os
        _kernels_module = False
        if not os.environ.get("CALIBKIT_NO_JIT"):
            try:
                from calibkit.vision import detect_kernels
                _kernels_module = detect_kernels
            except ImportError:
                pass
    return _kernels_module or None


# ---------------------------------------------------------------------------------------------
# Background level


def background_level(image: np.ndarray, mask: np.ndarray | None = None) -> tuple[float, float]:
    """(level, noise sigma) of the background: the median, and the spread of the differences
    between horizontally adjacent pixels.

    Markers cover a small part of the image, so the median is the background level. The
    noise comes from pixel-to-pixel differences (divided by sqrt 2), whose interquartile range
    ignores the few spots and, unlike the spread of the values, any smooth gradient of the
    lighting. A sparse grid of pixels is enough (the estimates agree with the full image's
    to a few per cent); histograms are interpolated within each integer bin so that noise
    below one DN is still measured.
    """
    return _background_level(image, mask, _kernels())


def _background_level(image: np.ndarray, mask: np.ndarray | None,
                      kernels) -> tuple[float, float]:
    if image.shape[1] < 2:
        return float(np.median(image)), 0.0
    sy = 12 if image.shape[0] >= 240 else 1
    sx = 8 if image.shape[1] >= 240 else 2
    if kernels is not None and image.dtype == np.uint8:
        has_mask = mask is not None
        return kernels.background_u8(image, mask if has_mask else _NO_MASK, has_mask, sy, sx)
    a = image[::sy, 0:-1:sx]
    b = image[::sy, 1::sx][:, :a.shape[1]]
    if mask is not None:
        keep = ~(mask[::sy, 0:-1:sx] | mask[::sy, 1::sx][:, :a.shape[1]])
        a, b = a[keep], b[keep]
    if a.size == 0:
        return 0.0, 0.0
    if image.dtype == np.uint8:
        m = a.size
        both = np.empty(2 * m, dtype=np.intp)  # values 0..255, then differences 256..766
        both[:m] = a.ravel()
        np.subtract(both[:m], b.ravel(), out=both[m:])
        both[m:] += 511
        hist = np.bincount(both, minlength=767)
        # One cumulative histogram for both: the differences' quantiles sit above all values.
        cdf = np.cumsum(hist)
        n_val = float(cdf[255])
        targets = np.array([0.5 * n_val, n_val + 0.25 * m, n_val + 0.75 * m])
        k = np.searchsorted(cdf, targets, side="left")
        below = np.where(k > 0, cdf[k - 1], 0)
        q = k - 0.5 + (targets - below) / np.maximum(hist[k], 1)
        level, q25, q75 = q[0], q[1] - 256, q[2] - 256
    else:
        a = a.ravel().astype(np.float64)
        level = float(np.median(a))
        q25, q75 = np.percentile(a - b.ravel(), [25.0, 75.0])
    return float(level), float((q75 - q25) / (1.349 * np.sqrt(2.0)))


_NO_MASK = np.zeros((1, 1), dtype=bool)  # stands in for "no mask" in compiled kernels


def auto_threshold(image: np.ndarray, config: DetectorConfig = DetectorConfig(),
                   mask: np.ndarray | None = None) -> float:
    """The threshold "auto" resolves to for this image."""
    level, sigma = background_level(image, mask)
    return level + max(config.auto_k * sigma, config.min_contrast)


# ---------------------------------------------------------------------------------------------
# Connected regions of a sparse set of pixels


def label_pixels(pix: np.ndarray, width: int) -> tuple[np.ndarray, int]:
    """8-connected regions of the pixels with sorted flat indices `pix` -> (label per pixel, n).

    Labels are numbered in raster order of each region's first pixel.
    """
    return _label_pixels(pix, width, _kernels())


def _label_pixels(pix: np.ndarray, width: int, kernels) -> tuple[np.ndarray, int]:
    if kernels is not None:
        return kernels.label_sorted(np.asarray(pix, dtype=np.int64), int(width))
    runs = _Runs.find(pix, width)
    return runs.pixel_labels(), runs.n


@dataclass
class _Runs:
    """Horizontal runs of bright pixels (sorted flat indices `pix`) and their regions."""

    pix: np.ndarray
    width: int
    starts: np.ndarray  # index into pix of each run's first pixel
    lengths: np.ndarray
    ry: np.ndarray  # row of each run
    rx0: np.ndarray  # first and last column of each run
    rx1: np.ndarray
    run_label: np.ndarray  # region of each run
    n: int  # number of regions

    @classmethod
    def find(cls, pix: np.ndarray, width: int) -> _Runs:
        """Runs, linked to the touching runs of the row above (8-connectivity)."""
        n = len(pix)
        if n == 0:
            z = np.zeros(0, dtype=np.int64)
            return cls(pix, width, z, z, z, z, z, z, 0)
        brk = np.empty(n, dtype=bool)
        brk[0] = True
        np.not_equal(pix[1:] - pix[:-1], 1, out=brk[1:])
        starts = np.flatnonzero(brk)
        first = pix[starts]
        ry = first // width
        rx0 = first - ry * width
        lengths = np.empty_like(starts)
        lengths[:-1] = starts[1:] - starts[:-1]
        lengths[-1] = n - starts[-1]
        rx1 = rx0 + lengths - 1
        if rx1.max() >= width:  # a run that wraps from one row's end to the next row
            brk[1:] |= pix[1:] % width == 0
            starts = np.flatnonzero(brk)
            first = pix[starts]
            ry = first // width
            rx0 = first - ry * width
            lengths = np.diff(starts, append=n)
            rx1 = rx0 + lengths - 1
        nruns = len(starts)
        # Keys put the runs on one line, row after row, with a gap so that neighbouring rows
        # never touch; the touching runs above form one contiguous range [lo, hi).
        stride = width + 3
        above = (ry - 1) * stride
        lo = np.searchsorted(ry * stride + rx1 + 1, above + rx0, side="left")
        hi = np.searchsorted(ry * stride + rx0 + 1, above + rx1 + 2, side="right")
        count = hi - lo
        parent = np.where(count > 0, lo, np.arange(nruns))
        # Pointer jumping: each run ends up pointing at the first run of its tree.
        while True:
            grand = parent[parent]
            if (grand == parent).all():
                break
            parent = grand
        multi = np.flatnonzero(count > 1)
        if len(multi):
            parent = _merge_trees(parent, lo, count, multi)
        is_root = parent == np.arange(nruns)
        blob_of_root = np.cumsum(is_root) - 1
        return cls(pix, width, starts, lengths, ry, rx0, rx1, blob_of_root[parent],
                   int(blob_of_root[-1] + 1))

    def pixel_labels(self) -> np.ndarray:
        return np.repeat(self.run_label, self.lengths)

    def regions(self, image: np.ndarray) -> _Regions:
        n, lab = self.n, self.run_label
        area = np.bincount(lab, weights=self.lengths, minlength=n)
        bbox = np.empty((4, n), dtype=np.int64)
        bbox[:2] = np.iinfo(np.int64).max
        bbox[2:] = -1
        np.minimum.at(bbox[0], lab, self.rx0)
        np.minimum.at(bbox[1], lab, self.ry)
        np.maximum.at(bbox[2], lab, self.rx1)
        np.maximum.at(bbox[3], lab, self.ry)
        peak = np.zeros(n)
        if n:
            run_peak = np.maximum.reduceat(image.reshape(-1)[self.pix], self.starts)
            np.maximum.at(peak, lab, run_peak.astype(np.float64))
        return _Regions(area, bbox.T, peak, self.pix, self.pixel_labels)


def _merge_trees(root: np.ndarray, lo: np.ndarray, count: np.ndarray,
                 multi: np.ndarray) -> np.ndarray:
    """Join trees that a run touching several runs above connects (U and V shapes)."""
    reps = count[multi] - 1
    first = np.repeat(lo[multi], reps)
    other = first + (np.arange(reps.sum()) - np.repeat(np.cumsum(reps) - reps, reps)) + 1
    a, b = root[first], root[other]
    differ = a != b
    if not differ.any():
        return root
    # Union-find over the few tree roots involved; a handful per image in practice.
    boss: dict[int, int] = {}

    def find(i: int) -> int:
        while boss.get(i, i) != i:
            i = boss[i]
        return i

    for i, j in zip(a[differ].tolist(), b[differ].tolist(), strict=True):
        ri, rj = find(i), find(j)
        if ri != rj:
            boss[max(ri, rj)] = min(ri, rj)
    keys = np.fromiter(boss.keys(), dtype=np.int64)
    target = np.array([find(int(k)) for k in keys], dtype=np.int64)
    remap = np.arange(len(root))
    remap[keys] = target
    return remap[root]


@dataclass
class _Regions:
    """Regions to measure: per region area, bbox (x0 y0 x1 y1), peak; and their pixels."""

    area: np.ndarray
    bbox: np.ndarray
    peak: np.ndarray
    pix: np.ndarray  # flat indices of all region pixels
    labels: Callable[[], np.ndarray]  # region of each of pix, computed when needed

    @classmethod
    def from_pixels(cls, image: np.ndarray, pix: np.ndarray, labels: np.ndarray,
                    n: int) -> _Regions:
        width = image.shape[1]
        ys = pix // width
        xs = pix - ys * width
        area = np.bincount(labels, minlength=n).astype(np.float64)
        bbox = np.empty((4, n), dtype=np.int64)
        bbox[:2] = np.iinfo(np.int64).max
        bbox[2:] = -1
        np.minimum.at(bbox[0], labels, xs)
        np.minimum.at(bbox[1], labels, ys)
        np.maximum.at(bbox[2], labels, xs)
        np.maximum.at(bbox[3], labels, ys)
        peak = np.zeros(n)
        np.maximum.at(peak, labels, image.reshape(-1)[pix].astype(np.float64))
        return cls(area, bbox.T, peak, pix, lambda: labels)


# ---------------------------------------------------------------------------------------------
# Measuring regions

def _measure(image: np.ndarray, regions: _Regions, config: DetectorConfig, threshold: float,
             ignore: np.ndarray | None, background: Callable[[], tuple[float, float]],
             label_value: int = 0) -> Blobs:
    """Filter regions by area; centroid and roundness over each region's window.

    A region's window is its bounding box grown by `window_margin_px`. Windows are gathered
    as fixed-size square blocks (a power of two, one size class for most frames) so that the
    sums are two small batched matrix products. Pixels of another region or masked pixels
    get no weight; which windows hold any is decided from bounding boxes and the mask's
    integral image, so the common case (isolated markers) skips the per-pixel check.
    """
    area, bbox = regions.area, regions.bbox
    keep = np.flatnonzero((area >= config.min_area) & (area <= config.max_area))
    if len(keep) == 0:
        return Blobs.empty(threshold)
    h, w = image.shape
    m = config.window_margin_px
    box = bbox[keep]
    ax0 = np.maximum(box[:, 0] - m, 0)
    ay0 = np.maximum(box[:, 1] - m, 0)
    ax1 = np.minimum(box[:, 2] + m, w - 1)
    ay1 = np.minimum(box[:, 3] + m, h - 1)
    flagged = _crowded(ax0, ay0, ax1, ay1, keep, bbox)
    if ignore is not None:
        flagged |= _masked_in(ignore, ax0, ay0, ax1, ay1)
    owner = None
    if flagged.any():
        owner = _owner_image((h, w))
        owner[regions.pix] = regions.labels() + 1
    try:
        ex, ey = ax1 - ax0 + 1, ay1 - ay0 + 1
        # Block sizes: every window up to 24 px shares one block as large as the largest of
        # them (most frames: one class); bigger ones go by powers of two.
        size = np.maximum(ex, ey)
        small = size <= 24
        block = 1 << np.ceil(np.log2(np.maximum(size, 2))).astype(np.int64)
        if small.any():
            block[small] = max(int(size[small].max()), 3)
        classes = np.unique(block)
        flat = image.reshape(-1)
        if len(classes) == 1:
            out = _window_moments(flat, owner, ignore, (h, w), keep + 1, ax0, ay0, ex, ey,
                                  int(classes[0]), background, flagged)
        else:
            out = np.empty((len(keep), 5))
            for k in classes:
                sel = np.flatnonzero(block == k)
                out[sel] = _window_moments(flat, owner, ignore, (h, w), keep[sel] + 1, ax0[sel],
                                           ay0[sel], ex[sel], ey[sel], int(k), background,
                                           flagged[sel])
    finally:
        if owner is not None:
            owner[regions.pix] = 0
    crowded = np.flatnonzero(flagged & (out[:, 2] > 0))
    # Deblend touching spots in multi mode (skipped on frames that are mostly noise or
    # glare, where thousands of regions touch and no centroid means much).
    if config.mode == "multi" and len(crowded) and len(crowded) * len(keep) <= 1 << 22:
        # The global level: a crowded window's ring slopes with its neighbour's halo.
        level = np.full(len(out), background()[0])
        out[crowded, :2] = _deblend(image, out[:, :2], level, crowded, ax0, ay0, ax1, ay1,
                                    box, ignore)
    ok = (out[:, 2] > 0) & (out[:, 3] >= config.min_roundness)
    sel = keep[ok]
    return Blobs(out[ok, :2], area[sel], regions.peak[sel], bbox[sel], out[ok, 3],
                 np.full(len(sel), label_value), threshold)


def _deblend(image, uv, bg, crowded, ax0, ay0, ax1, ay1, box, ignore,
             iterations: int = 3) -> np.ndarray:
    """Centroids of spots whose windows hold a neighbour, with the light shared out.

    Symmetric-template deblending (as in the SDSS photometric pipeline): a round spot looks
    the same mirrored through its centre, so min(I(p), I(2c - p)) bounds its light at p.
    Each pixel of a crowded window gives the spot its share of the light, template over the
    sum of the templates of the spot and its neighbours, and the centroid is taken again;
    a few rounds settle it. Without this a touching neighbour's skirt pulls the centroid
    towards it by tenths of a pixel.
    """
    h, w = image.shape
    flat = image.reshape(-1).astype(np.float64)
    # Neighbours: other blobs whose box meets this window.
    hit = ((box[None, :, 0] <= ax1[crowded, None]) & (box[None, :, 2] >= ax0[crowded, None])
           & (box[None, :, 1] <= ay1[crowded, None]) & (box[None, :, 3] >= ay0[crowded, None]))
    hit[np.arange(len(crowded)), crowded] = False
    n_nb = hit.sum(axis=1)
    m = max(int(n_nb.max()), 1)
    nb = np.zeros((len(crowded), m), dtype=np.int64)
    nb_ok = np.arange(m)[None, :] < n_nb[:, None]
    nb[nb_ok] = np.nonzero(hit)[1]
    members = np.concatenate([crowded[:, None], nb], axis=1)  # (c, m + 1): self first
    valid_member = np.concatenate([np.ones((len(crowded), 1), bool), nb_ok], axis=1)
    kx = int((ax1 - ax0)[crowded].max()) + 1
    ky = int((ay1 - ay0)[crowded].max()) + 1
    xs = ax0[crowded, None] + np.arange(kx)  # (c, kx)
    ys = ay0[crowded, None] + np.arange(ky)
    inside = ((ys <= ay1[crowded, None])[:, :, None] & (xs <= ax1[crowded, None])[:, None, :])
    xs_c, ys_c = np.minimum(xs, w - 1), np.minimum(ys, h - 1)
    pix = ys_c[:, :, None] * w + xs_c[:, None, :]  # (c, ky, kx)
    if ignore is not None:
        inside &= ~ignore.reshape(-1)[pix]
    light = flat[pix] - bg[crowded, None, None]
    xg = xs[:, None, :].astype(np.float64)
    yg = ys[:, :, None].astype(np.float64)
    centres = uv.copy()
    for _ in range(iterations):
        # Mirror each window pixel through each member's centre; the image between pixels
        # is interpolated bilinearly.
        qx = 2.0 * centres[members][:, :, 0, None, None] - xs[:, None, None, :]
        qy = 2.0 * centres[members][:, :, 1, None, None] - ys[:, None, :, None]
        qx, qy = np.broadcast_arrays(np.clip(qx, 0, w - 1.001), np.clip(qy, 0, h - 1.001))
        x0 = np.floor(qx).astype(np.int64)
        y0 = np.floor(qy).astype(np.int64)
        fx, fy = qx - x0, qy - y0
        i00 = y0 * w + x0
        mirrored = ((flat[i00] * (1 - fx) + flat[i00 + 1] * fx) * (1 - fy)
                    + (flat[i00 + w] * (1 - fx) + flat[i00 + w + 1] * fx) * fy)
        mirrored -= bg[members][:, :, None, None]  # (c, m + 1, ky, kx)
        tmpl = np.maximum(np.minimum(light[:, None], mirrored), 0.0)
        tmpl *= valid_member[:, :, None, None]
        total = tmpl.sum(axis=1)
        share = np.where(total > 0, tmpl[:, 0] / np.where(total > 0, total, 1.0), 1.0)
        wt = light * share * inside
        s0 = wt.sum(axis=(1, 2))
        good = s0 > 0
        s0 = np.where(good, s0, 1.0)
        new = np.stack([(wt * xg).sum(axis=(1, 2)) / s0, (wt * yg).sum(axis=(1, 2)) / s0],
                       axis=1)
        centres[crowded] = np.where(good[:, None], new, centres[crowded])
    return centres[crowded]


def _crowded(ax0, ay0, ax1, ay1, keep, bbox) -> np.ndarray:
    """Which windows overlap the bounding box of another region (any region, kept or not)."""
    if len(keep) * len(bbox) > 1 << 16:
        return np.ones(len(keep), dtype=bool)
    hit = ((bbox[None, :, 0] <= ax1[:, None]) & (bbox[None, :, 2] >= ax0[:, None])
           & (bbox[None, :, 1] <= ay1[:, None]) & (bbox[None, :, 3] >= ay0[:, None]))
    hit[np.arange(len(keep)), keep] = False
    return hit.any(axis=1)


_scratch = threading.local()  # per-thread caches: cameras detect in their own threads


def _owner_image(shape: tuple[int, int]) -> np.ndarray:
    """A flat int32 scratch image (zero between calls) for "which region owns this pixel"."""
    img = getattr(_scratch, "owner", None)
    if img is None or img.size != shape[0] * shape[1]:
        img = np.zeros(shape[0] * shape[1], dtype=np.int32)
        _scratch.owner = img
    return img


def _masked_in(ignore: np.ndarray, ax0, ay0, ax1, ay1) -> np.ndarray:
    """Which windows hold a masked pixel, from the mask's integral image (cached per mask)."""
    cached = getattr(_scratch, "mask", None)
    if cached is None or cached[0] is not ignore:
        integral = cv2.integral(ignore.view(np.uint8))  # (h+1, w+1)
        cached = (ignore, integral)
        _scratch.mask = cached
    s = cached[1]
    total = s[ay1 + 1, ax1 + 1] - s[ay0, ax1 + 1] - s[ay1 + 1, ax0] + s[ay0, ax0]
    return total > 0


_tables: dict[int, tuple[np.ndarray, np.ndarray]] = {}


def _window_table(k: int, lo: np.ndarray, length: np.ndarray, open_lo: np.ndarray,
                  open_hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For windows [lo, lo + length) in a block of k: (b, 6, k) rows: the window's indicator
    times 1, c, c^2, then its interior's indicator times 1, c, c^2 (c: block coordinate about
    the block centre); and their (b, 6) sums. The interior is the window shrunk by one pixel
    except on sides cut by the image edge (open_lo, open_hi), so the ring around it never
    lies on a spot the edge cuts through. Tabulated for small blocks."""
    if k > 24:  # large blobs are rare: compute their rows instead of tabulating k^3 values
        c = np.arange(k)
        lo_, hi_ = lo[:, None], (lo + length)[:, None]
        ind = (c >= lo_) & (c < hi_)
        inner = (c > lo_ - open_lo[:, None]) & (c < hi_ - 1 + open_hi[:, None])
        cc = c - (k - 1) * 0.5
        rows = np.stack([ind * 1.0, ind * cc, ind * cc * cc,
                         inner * 1.0, inner * cc, inner * cc * cc], axis=1)
        return rows, rows.sum(axis=2)
    got = _tables.get(k)
    if got is None:
        c = np.arange(k)
        los = np.arange(k)[:, None, None, None, None]
        lens = np.arange(k + 1)[None, :, None, None, None]
        cut_lo = np.arange(2)[None, None, :, None, None]
        cut_hi = np.arange(2)[None, None, None, :, None]
        ind = (c >= los) & (c < los + lens)
        inner = (c > los - cut_lo) & (c < los + lens - 1 + cut_hi)
        cc = c - (k - 1) * 0.5
        ind, inner = np.broadcast_arrays(ind, inner)
        rows = np.stack([ind * 1.0, ind * cc, ind * cc * cc,
                         inner * 1.0, inner * cc, inner * cc * cc], axis=4)
        got = (rows.reshape(-1, 6, k), rows.sum(axis=5).reshape(-1, 6))
        if len(_tables) >= 8:
            _tables.clear()
        _tables[k] = got
    at = ((lo * (k + 1) + length) * 2 + open_lo.astype(np.intp)) * 2 + open_hi.astype(np.intp)
    return got[0].take(at, axis=0), got[1].take(at, axis=0)


# A background slope is used only when it stands out of the noise this clearly (chi-square,
# 2 degrees of freedom, p = 0.001): fitting a plane to a flat ring would only add noise.
_SLOPE_CHI2 = 13.8


def _window_moments(flat_img, owner, ignore, shape, own_label, ax0, ay0, ex, ey, k,
                    background, flagged) -> np.ndarray:
    """Columns u, v, weight sum, roundness for blobs whose windows fit a k x k block.

    All sums come from S = My V Mx^T, where V is the block of pixel values and the rows of
    Mx (My) are the window's indicator times 1, x, x^2 (y, y^2), and the indicator of the
    window shrunk by one pixel: S[i, j] is then the sum over the window of V y^i x^j, and
    the ring (window minus its shrunk interior) gives the local background.
    """
    h, w = shape
    kx, ky = min(k, w), min(k, h)
    # Block origins, shifted inwards at the image edges (the window stays inside the block).
    ox = np.minimum(ax0, w - kx)
    oy = np.minimum(ay0, h - ky)
    idx = (oy * w + ox)[:, None, None] + _block_offsets(ky, kx, w)
    vals = flat_img.take(idx).astype(np.float64)
    mx, nx = _window_table(kx, ax0 - ox, ex, ax0 == 0, ax0 + ex == w)  # (b, 6, kx), (b, 6)
    my, ny = _window_table(ky, ay0 - oy, ey, ay0 == 0, ay0 + ey == h)
    mxt = mx.transpose(0, 2, 1)
    n = ny[:, :, None] * nx[:, None, :]  # pixel counts and coordinate sums of the window
    crowded = np.flatnonzero(flagged)
    if len(crowded):  # another region or masked pixels inside these windows: no weight there
        own = owner.take(idx[crowded])
        mine = own_label[crowded, None, None]
        keep_px = (own == mine) | (own == 0)
        if ignore is not None:
            keep_px &= ~ignore.reshape(-1).take(idx[crowded])
        vals[crowded] *= keep_px
        n[crowded] = my[crowded] @ (keep_px @ mxt[crowded])
    s = my @ (vals @ mxt)  # (b, 6, 6)
    # The ring (window minus interior): fit the background as a constant, or as a plane
    # where it slopes significantly (a lamp's skirt, vignetting, a neighbour's halo).
    # Ring sums of v, v x, v y, and of 1, x, y, x^2, y^2, x y (its pixel coordinates).
    ring = s[:, :3, :3] - s[:, 3:, 3:]
    ringn = n[:, :3, :3] - n[:, 3:, 3:]
    r0, rx, ry = ring[:, 0, 0], ring[:, 0, 1], ring[:, 1, 0]
    ring_n = ringn[:, 0, 0]
    inv_n = 1.0 / np.maximum(ring_n, 1.0)
    b0 = r0 * inv_n
    # Plane v = b0 + bx x + by y by least squares, written with the ring's centred moments
    # (2 x 2 in the slopes); the slopes' chi-square against the noise is slope' C slope.
    mx_r, my_r = ringn[:, 0, 1] * inv_n, ringn[:, 1, 0] * inv_n
    cxx_r = ringn[:, 0, 2] - ringn[:, 0, 1] * mx_r
    cyy_r = ringn[:, 2, 0] - ringn[:, 1, 0] * my_r
    cxy_r = ringn[:, 1, 1] - ringn[:, 0, 1] * my_r
    gx, gy = rx - r0 * mx_r, ry - r0 * my_r
    det = cxx_r * cyy_r - cxy_r * cxy_r
    ok_det = det > 1e-6 * np.maximum(cxx_r * cyy_r, 1e-12)
    det = np.where(ok_det, det, 1.0)
    bx = (cyy_r * gx - cxy_r * gy) / det
    by = (cxx_r * gy - cxy_r * gx) / det
    chi2 = bx * gx + by * gy  # = slope' C slope
    sigma = max(background()[1], 0.5) if len(ox) else 1.0
    strong = ok_det & (ring_n >= 8) & (chi2 > _SLOPE_CHI2 * sigma * sigma)
    bx = np.where(strong, bx, 0.0)
    by = np.where(strong, by, 0.0)
    b0 = np.where(strong, b0 - bx * mx_r - by * my_r, b0)
    if not np.all(ring_n > 0):  # windows that fill the image: the image's background level
        b0[ring_n <= 0] = background()[0]
    t = (s[:, :3, :3] - b0[:, None, None] * n[:, :3, :3]).reshape(-1, 9)  # minus background
    # The plane's slope terms for the zeroth and first moments (second moments keep the
    # constant part only: their slope terms are odd and nearly cancel over the window).
    t[:, 0] -= bx * n[:, 0, 1] + by * n[:, 1, 0]
    t[:, 1] -= bx * n[:, 0, 2] + by * n[:, 1, 1]
    t[:, 3] -= bx * n[:, 1, 1] + by * n[:, 2, 0]
    s0 = t[:, 0]
    good = s0 > 0
    t /= np.where(good, s0, 1.0)[:, None]
    mean_x, mean_y = t[:, 1], t[:, 3]  # about the block centre
    # Roundness: the axis ratio of the second moments; a pixel's own extent (1/12) keeps
    # one-pixel spots round rather than degenerate.
    cxx = np.maximum(t[:, 2] - mean_x * mean_x, 0.0) + 1.0 / 12.0
    cyy = np.maximum(t[:, 6] - mean_y * mean_y, 0.0) + 1.0 / 12.0
    cxy = t[:, 4] - mean_x * mean_y
    half_tr = 0.5 * (cxx + cyy)
    disc = np.sqrt(0.25 * (cxx - cyy) ** 2 + cxy * cxy)
    out = np.empty((len(ox), 5))
    out[:, 0] = ox + (kx - 1) * 0.5 + mean_x
    out[:, 1] = oy + (ky - 1) * 0.5 + mean_y
    out[:, 2] = np.where(good, s0, 0.0)
    out[:, 3] = np.sqrt(np.maximum(half_tr - disc, 0.0) / (half_tr + disc))
    out[:, 4] = b0
    return out


_offsets_cache: dict[tuple[int, int, int], np.ndarray] = {}


def _block_offsets(ky: int, kx: int, width: int) -> np.ndarray:
    key = (ky, kx, width)
    offs = _offsets_cache.get(key)
    if offs is None:
        offs = (np.arange(ky)[:, None] * width + np.arange(kx)[None, :]).astype(np.intp)
        if len(_offsets_cache) > 64:
            _offsets_cache.clear()
        _offsets_cache[key] = offs
    return offs


# ---------------------------------------------------------------------------------------------
# Detection


def detect(image: np.ndarray, config: DetectorConfig = DetectorConfig()) -> Blobs:
    """Find the markers in one image: grayscale (h, w) or BGR colour (h, w, 3)."""
    return _detect(image, config, _kernels())


def detect_reference(image: np.ndarray, config: DetectorConfig = DetectorConfig()) -> Blobs:
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
        level, sigma = _background_level(image, mask, kernels)
        threshold = level + max(config.auto_k * sigma, config.min_contrast)

        def background() -> tuple[float, float]:
            return level, sigma
    else:
        threshold = float(config.threshold)

        def background() -> tuple[float, float]:
            return _background_level(image, mask, kernels)
    if maxima is not None:
        return _detect_compiled(kernels, image, maxima, threshold, config, mask, background)
    pix = _bright_pixels(image, threshold, mask)
    if config.mode == "multi":
        return _detect_multi(image, pix, threshold, config, mask, background, kernels)
    regions = _Runs.find(pix, image.shape[1]).regions(image)
    return _measure(image, regions, config, threshold, mask, background)


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
    (both contiguous): what _Runs.find, _Runs.regions and _measure do, compiled."""
    has_mask = mask is not None
    mask = np.ascontiguousarray(mask) if has_mask else _NO_MASK
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


def _bright_pixels(image: np.ndarray, threshold: float, mask: np.ndarray | None) -> np.ndarray:
    """Sorted flat indices of the pixels brighter than `threshold` and not masked."""
    if image.dtype == np.uint8:
        if threshold >= 255:
            return np.zeros(0, dtype=np.int64)
        above = image > np.uint8(max(int(np.floor(threshold)), 0))
        if above.size % 8 == 0 and above.flags.c_contiguous:
            # Scan 8 pixels at a time: markers are sparse, so only a few words hold any.
            words = above.reshape(-1).view(np.uint64)
            hit = np.flatnonzero(words != 0)
            bits = np.flatnonzero(words[hit].view(np.bool_))
            pix = hit[bits >> 3] * 8 + (bits & 7)
        else:
            pix = np.flatnonzero(above)
    else:
        pix = np.flatnonzero(image > threshold)
    if mask is not None:
        pix = pix[~mask.reshape(-1)[pix]]
    return pix


def _detect_hsv(bgr: np.ndarray, config: DetectorConfig, mask: np.ndarray | None,
                kernels) -> Blobs:
    """One pass per HSV range over the same image; brightness (V) weights the centroid."""
    if bgr.dtype != np.uint8:
        raise UserError(f"HSV detection needs an 8-bit colour image, got {bgr.dtype}")
    hsv = cv2.cvtColor(np.ascontiguousarray(bgr), cv2.COLOR_BGR2HSV)
    value = np.ascontiguousarray(hsv[:, :, 2])
    level, sigma = _background_level(value, mask, kernels)

    def background() -> tuple[float, float]:
        return level, sigma
    parts = []
    for index, (lo, hi) in enumerate(config.hsv_ranges):
        if lo[0] <= hi[0]:
            inside = cv2.inRange(hsv, np.array(lo), np.array(hi))
        else:  # the hue range wraps around red: lo..179 or 0..hi
            inside = cv2.inRange(hsv, np.array(lo), np.array((179, *hi[1:])))
            inside |= cv2.inRange(hsv, np.array((0, *lo[1:])), np.array(hi))
        if kernels is not None:
            parts.append(_measure_compiled(kernels, inside, np.uint8(0), value, config, level,
                                           mask, background, index))
            continue
        above = inside > 0
        if mask is not None:
            above &= ~mask
        pix = np.flatnonzero(above)
        regions = _Runs.find(pix, bgr.shape[1]).regions(value)
        parts.append(_measure(value, regions, config, level, mask, background, index))
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
        lab, nreg = _label_pixels(pix, w, kernels)
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
    regions = _Regions.from_pixels(image, pix, labels, len(found))
    return _measure(image, regions, config, threshold, mask, background)
