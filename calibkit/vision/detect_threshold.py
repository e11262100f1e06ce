"""Detection's thresholding: the background level and noise, the automatic threshold, the
pixels above a threshold, and HSV colour filters (calibkit.vision.detect runs them)."""

from __future__ import annotations

import cv2
import numpy as np

from calibkit.vision.detect_config import DetectorConfig, jit_kernels


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
    return estimate_background(image, mask, jit_kernels())


def estimate_background(image: np.ndarray, mask: np.ndarray | None,
                        kernels) -> tuple[float, float]:
    """background_level with the compiled kernels given (None: in numpy)."""
    if image.shape[1] < 2:
        return float(np.median(image)), 0.0
    sy = 12 if image.shape[0] >= 240 else 1
    sx = 8 if image.shape[1] >= 240 else 2
    if kernels is not None and image.dtype == np.uint8:
        has_mask = mask is not None
        return kernels.background_u8(image, mask if has_mask else NO_MASK, has_mask, sy, sx)
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


NO_MASK = np.zeros((1, 1), dtype=bool)  # stands in for "no mask" in compiled kernels


def auto_threshold(image: np.ndarray, config: DetectorConfig = DetectorConfig(),  # noqa: B008
                   mask: np.ndarray | None = None) -> float:
    """The threshold "auto" resolves to for this image."""
    level, sigma = background_level(image, mask)
    return level + max(config.auto_k * sigma, config.min_contrast)


def bright_pixels(image: np.ndarray, threshold: float, mask: np.ndarray | None) -> np.ndarray:
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


def hsv_inside(hsv: np.ndarray, lo, hi) -> np.ndarray:
    """uint8 (h, w), 255 where an HSV image (OpenCV's, H 0..179) lies in the range lo..hi;
    a low hue above the high one wraps around red (lo..179 or 0..hi)."""
    if lo[0] <= hi[0]:
        return cv2.inRange(hsv, np.array(lo), np.array(hi))
    inside = cv2.inRange(hsv, np.array(lo), np.array((179, *hi[1:])))
    inside |= cv2.inRange(hsv, np.array((0, *lo[1:])), np.array(hi))
    return inside
