"""Measuring detected regions: area filter, windowed background-subtracted centroids,
roundness, and the deblending of touching spots.

The centroid is the intensity-weighted mean position with the local background
subtracted, taken over a window a little larger than the thresholded region: weighting only
the pixels above the threshold would cut off the spot's skirt unevenly whenever the spot is
not centred on a pixel, and bias the centroid towards the pixel grid ("pixel locking").
All per-blob sums are batched matrix products over gathered windows: no Python loop per
blob.
"""

from __future__ import annotations

import threading
from collections.abc import Callable

import cv2
import numpy as np

from calibkit.vision.detect_config import Blobs, DetectorConfig
from calibkit.vision.detect_regions import Regions


def measure_regions(image: np.ndarray, regions: Regions, config: DetectorConfig,
                    threshold: float, ignore: np.ndarray | None,
                    background: Callable[[], tuple[float, float]],
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
