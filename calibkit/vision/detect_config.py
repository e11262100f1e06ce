"""What the marker detector takes and gives: DetectorConfig (what counts as a marker) and
Blobs (the markers found), and the switch between its compiled kernels and numpy.

The detector itself is calibkit.vision.detect; its stages are detect_threshold (the
background level, the threshold, bright pixels, HSV colour filters), detect_regions
(connected regions of the bright pixels) and detect_centroids (windowed, background-
subtracted centroids and roundness).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field, replace

import numpy as np

from calibkit.core.errors import UserError
from calibkit.vision import detect_kernels

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
        return replace(self, **changes)


_kernels_module = None


def jit_kernels():
    """calibkit.vision.detect_kernels (numba, imported on first use: it costs ~0.5 s), or None
    where numba is missing or CALIBKIT_NO_JIT is set: detection then runs in numpy."""
    global _kernels_module
    if _kernels_module is None:
        _kernels_module = False
        if not os.environ.get("CALIBKIT_NO_JIT"):
            try:
                _kernels_module = detect_kernels
            except ImportError:
                pass
    return _kernels_module or None
