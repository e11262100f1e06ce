"""Images of marker spots as a camera sees them: blurred, area-integrated discs plus sensor noise.

The simulator draws every marker image with `render_spots`, and the detector's accuracy is
measured against the centres given here, so the centres must be exact: a spot's image is
the disc convolved with a Gaussian point-spread function and integrated over each pixel's
area (pixel centres at integer coordinates), and that is computed as one small matrix
product per spot rather than by point-sampling (which would bias centroids towards pixel
centres, "pixel locking").

How: the disc is anti-aliased onto a fine sub-grid (S x S samples per pixel), and each
pixel's value is the sub-grid weighted by the pixel box convolved with the Gaussian. That
kernel is separable and the same for every spot (windows are aligned to whole pixels), so a
spot's window is `A @ disc @ A.T` with one matrix `A`; all spots of one window size go
through a single batched matmul.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.special import ndtr

SUBSAMPLES = 8  # sub-grid samples per pixel along each axis
_SIGMA_SPAN = 4.0  # the window reaches this many blur sigmas beyond the disc's edge


def _pixel_kernel(k: int, kd: int, blur_px: float) -> np.ndarray:
    """(k, kd*S) weights from sub-grid samples to pixels: the pixel box convolved with the blur.

    The output window has k pixels and the disc's sub-grid spans the central kd pixels of
    it. Row p holds, for each sub-sample position x_s, the integral over pixel p's box of a
    Gaussian centred at x_s (times the sub-sample width), so that summing the disc coverage
    against it integrates (disc * Gaussian) over the pixel.
    """
    s = SUBSAMPLES
    pix = np.arange(k, dtype=np.float64)[:, None]
    sub = (k - kd) // 2 + (np.arange(kd * s, dtype=np.float64) + 0.5) / s - 0.5
    off = pix - sub[None, :]
    if blur_px > 0:
        box = ndtr((off + 0.5) / blur_px) - ndtr((off - 0.5) / blur_px)
    else:
        box = (np.abs(off) < 0.5).astype(np.float64)
    return (box / s).astype(np.float32)


def render_spots_float(size: tuple[int, int], uv, radius_px, peak=200.0,
                       blur_px: float = 0.5) -> np.ndarray:
    """The noise-free spot signal (float32 (h, w), DN above the background), unclipped.

    A disc that covers a whole pixel contributes `peak` DN to it (before blur); overlapping
    spots add.
    """
    w, h = int(size[0]), int(size[1])
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    n = len(uv)
    radius = np.broadcast_to(np.asarray(radius_px, dtype=np.float64), (n,))
    amp = np.broadcast_to(np.asarray(peak, dtype=np.float64), (n,))
    out = np.zeros(h * w, dtype=np.float32)
    ok = np.isfinite(uv).all(axis=1) & np.isfinite(radius) & (radius > 0) & (amp != 0)
    blur = max(float(blur_px), 0.0)
    half = np.zeros(n, dtype=np.int64)  # output window half-width, pixels
    half_disc = np.zeros(n, dtype=np.int64)  # the disc's sub-grid half-width, pixels
    half[ok] = np.ceil(radius[ok] + _SIGMA_SPAN * blur + 1.0).astype(np.int64)
    half_disc[ok] = np.ceil(radius[ok] + 0.5).astype(np.int64)
    # Spots wholly outside the image contribute nothing.
    ok &= (uv[:, 0] + half >= 0) & (uv[:, 0] - half <= w - 1)
    ok &= (uv[:, 1] + half >= 0) & (uv[:, 1] - half <= h - 1)
    s = SUBSAMPLES
    groups = np.unique(np.stack([half[ok], half_disc[ok]], axis=1), axis=0)
    for hk, hd in groups:
        idx = np.flatnonzero(ok & (half == hk) & (half_disc == hd))
        k, kd = 2 * int(hk) + 1, 2 * int(hd) + 1
        a = _pixel_kernel(k, kd, blur)
        centre = np.rint(uv[idx]).astype(np.int64)  # window centre pixel
        origin = centre - hk  # pixel coordinate of the window's first pixel
        # Sub-sample positions relative to the spot centre (small numbers: float32 is exact
        # enough and halves the work).
        sub = (np.arange(kd * s, dtype=np.float64) + 0.5) / s - 0.5 - hd
        dx = ((centre[:, 0] - uv[idx, 0])[:, None] + sub[None, :]).astype(np.float32)
        dy = ((centre[:, 1] - uv[idx, 1])[:, None] + sub[None, :]).astype(np.float32)
        d = dx[:, None, :] ** 2 + dy[:, :, None] ** 2
        np.sqrt(d, out=d)
        # Coverage of each sub-sample cell, anti-aliased over the cell's width.
        rs = (radius[idx] * s + 0.5).astype(np.float32)[:, None, None]
        d *= -s
        d += rs
        np.clip(d, 0.0, 1.0, out=d)
        win = a[None] @ d @ a.T[None]  # (m, k, k): rows y, columns x
        win *= amp[idx, None, None].astype(np.float32)
        xs = origin[:, 0, None] + np.arange(k)[None, :]  # (m, k)
        ys = origin[:, 1, None] + np.arange(k)[None, :]
        inside = ((ys >= 0) & (ys < h))[:, :, None] & ((xs >= 0) & (xs < w))[:, None, :]
        flat = ys[:, :, None] * w + xs[:, None, :]
        np.add.at(out, flat[inside], win[inside])
    return out.reshape(h, w)


def render_spots(size: tuple[int, int], uv, radius_px, peak=200.0, background: float = 8.0,
                 noise_sigma: float = 2.0, blur_px: float = 0.5, rng=None,
                 shot_gain: float = 0.025) -> np.ndarray:
    """An 8-bit image (h, w) of bright spots at sub-pixel centres `uv` (N, 2), as a sensor gives.

    radius_px, peak: per spot (N,) or one value; peak is the DN a fully covered pixel gains
    before blur. background: the dark/ambient level in DN. noise_sigma: read noise in DN.
    shot_gain: DN per photo-electron, so shot noise has variance shot_gain * signal (0 turns
    it off). rng: a numpy Generator or a seed; the same rng state gives the same image.
    Values are rounded and clipped to 0..255 like an 8-bit sensor.
    """
    w, h = int(size[0]), int(size[1])
    if w <= 0 or h <= 0:
        raise ValueError(f"image size must be positive, got {size}")
    signal = render_spots_float((w, h), uv, radius_px, peak, blur_px)
    signal += np.float32(background)
    var = np.float32(noise_sigma) ** 2
    if shot_gain > 0:
        var = var + np.float32(shot_gain) * np.maximum(signal, 0.0)
    if np.any(var > 0):
        rng = np.random.default_rng(rng)
        noise = rng.standard_normal((h, w), dtype=np.float32)
        noise *= np.sqrt(var, dtype=np.float32) if np.ndim(var) else np.float32(math.sqrt(var))
        signal += noise
    np.rint(signal, out=signal)
    np.clip(signal, 0, 255, out=signal)
    return signal.astype(np.uint8)
