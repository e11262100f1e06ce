"""Compiled (numba) kernels for marker detection's hot path, second half: each region's
windowed, background-subtracted moments (calibkit.vision.detect_kernels finds the regions).

Why compiled, how it is checked against the numpy reference and where it is cached: see
calibkit.vision.detect_kernels; the same holds here (every sum is exact in any order).
"""

from __future__ import annotations

import numpy as np

from calibkit.core.jit import jit

# as calibkit.vision.detect_centroids: chi-square (2 dof, p = 0.001) for a sloping ring
_SLOPE_CHI2 = 13.8

# ---------------------------------------------------------------------------------------------
# Windowed, background-subtracted moments


@jit
def measure(values, candidates, tint, mask, has_mask, runs, run_label, area, bbox, peak,
            min_area, max_area, min_roundness, margin, level, sigma):
    """calibkit.vision.detect_centroids.measure_regions for the single-threshold mode, one
    window at a time.

    Regions inside the area range are measured over their bounding box grown by `margin`;
    pixels of another region and masked pixels get no weight. Coordinates are taken about
    the centre of the block the numpy reference gathers the window into, so that the
    second moments (and roundness) are the same where the ring's plane fit applies.
    Returns the kept blobs: uv (n, 2), area, peak, bbox (n, 4), roundness.
    """
    h, w = values.shape
    keep = np.flatnonzero((area >= min_area) & (area <= max_area))
    nk = len(keep)
    box = np.empty((nk, 4), dtype=np.int64)
    for b in range(nk):
        k = keep[b]
        box[b, 0] = max(bbox[k, 0] - margin, 0)
        box[b, 1] = max(bbox[k, 1] - margin, 0)
        box[b, 2] = min(bbox[k, 2] + margin, w - 1)
        box[b, 3] = min(bbox[k, 3] + margin, h - 1)
    block = _block_sizes(box)
    res = np.empty((nk, 5))
    acc = np.empty(21)
    for b in range(nk):
        _window(values, candidates, tint, mask, has_mask, runs, run_label, keep[b],
                area[keep[b]], box[b], block[b], level, sigma, acc, res[b])
    ok = np.flatnonzero((res[:, 2] > 0) & (res[:, 3] >= min_roundness))
    sel = keep[ok]
    return res[ok, :2], area[sel], peak[sel], bbox[sel], res[ok, 3]


@jit
def _block_sizes(box):
    """The reference's block size per window: windows up to 24 px share the size of the
    largest of them (at least 3); bigger ones round up to a power of two."""
    nk = len(box)
    size = np.empty(nk, dtype=np.int64)
    small_max = -1
    for b in range(nk):
        size[b] = max(box[b, 2] - box[b, 0] + 1, box[b, 3] - box[b, 1] + 1)
        if size[b] <= 24:
            small_max = max(small_max, size[b])
    block = np.empty(nk, dtype=np.int64)
    for b in range(nk):
        if size[b] <= 24:
            block[b] = max(small_max, 3)
        else:
            k = 1
            while k < size[b]:
                k *= 2
            block[b] = k
    return block


@jit
def _window(values, candidates, tint, mask, has_mask, runs, run_label, label, region_area,
            box, k, level, sigma, acc, out):
    """Centroid, weight, roundness and background of one window into out (u, v, s0,
    roundness, b0): the background is the ring's mean, or its plane where it slopes.

    acc (21,) is scratch for the sums: of the window, v times 1, x, x^2, y, x y, y^2 and
    the same of 1 (pixel count and coordinate sums); of the interior (the window shrunk by
    one pixel, except on sides the image edge cuts), v times 1, x, y and 1, x, x^2, y, x y,
    y^2."""
    h, w = values.shape
    ax0, ay0, ax1, ay1 = box[0], box[1], box[2], box[3]
    kx, ky = min(k, w), min(k, h)
    ox, oy = min(ax0, w - kx), min(ay0, h - ky)
    cx, cy = (kx - 1) * 0.5, (ky - 1) * 0.5
    ix0 = ax0 + 1 - (1 if ax0 == 0 else 0)
    ix1 = ax1 - 1 + (1 if ax1 == w - 1 else 0)
    iy0 = ay0 + 1 - (1 if ay0 == 0 else 0)
    iy1 = ay1 - 1 + (1 if ay1 == h - 1 else 0)
    acc[:] = 0.0
    if _window_is_clean(candidates, tint, mask, has_mask, box, region_area):
        _sums_clean(values, box, ox, oy, cx, cy, ix0, ix1, iy0, iy1, acc)
    else:
        _sums_checked(values, candidates, tint, mask, has_mask, runs, run_label, label, box,
                      ox, oy, cx, cy, ix0, ix1, iy0, iy1, acc)
    _background_and_moments(acc[0:6], acc[6:12], acc[12:15], acc[15:21], level, sigma, out)
    out[0] += ox + cx
    out[1] += oy + cy


@jit
def _window_is_clean(candidates, tint, mask, has_mask, box, region_area):
    """No masked pixel and no pixel of another region in the window (the common case): the
    window's candidate pixels are exactly its own region's."""
    count = 0
    masked = False
    for y in range(box[1], box[3] + 1):
        for x in range(box[0], box[2] + 1):
            count += candidates[y, x] > tint
        if has_mask:
            for x in range(box[0], box[2] + 1):
                masked |= mask[y, x]
    return count == region_area and not masked


@jit
def _sums_clean(values, box, ox, oy, cx, cy, ix0, ix1, iy0, iy1, acc):
    """The window sums where every pixel counts: a row's interior sums are its window sums
    less the end pixels that lie on the ring."""
    ax0, ay0, ax1, ay1 = box[0], box[1], box[2], box[3]
    c0 = c1 = c2 = j0 = j1 = j2 = 0.0  # per row: counts and coordinate sums
    for x in range(ax0, ax1 + 1):
        xc = float(x - ox) - cx
        c0 += 1.0
        c1 += xc
        c2 += xc * xc
        if ix0 <= x <= ix1:
            j0 += 1.0
            j1 += xc
            j2 += xc * xc
    xl, xr = float(ax0 - ox) - cx, float(ax1 - ox) - cx
    w = values.shape[1]
    flat = values.reshape(-1)
    for y in range(ay0, ay1 + 1):
        yc = float(y - oy) - cy
        # Integer sums about the block's first column (twice as fast as floats), then
        # moved to its centre: exact either way, pixel values are integers.
        s0 = s1 = s2 = 0
        base = y * w
        for x in range(ax0, ax1 + 1):
            v = np.int64(flat[base + x])
            dx = x - ox
            s0 += v
            s1 += v * dx
            s2 += v * (dx * dx)
        a0 = float(s0)
        a1 = s1 - cx * s0
        a2 = s2 - 2.0 * cx * s1 + cx * cx * s0
        _add_row(acc, yc, a0, a1, a2, c0, c1, c2)
        if iy0 <= y <= iy1:
            i0, i1 = a0, a1
            if ix0 > ax0:
                vl = float(values[y, ax0])
                i0 -= vl
                i1 -= vl * xl
            if ix1 < ax1:
                vr = float(values[y, ax1])
                i0 -= vr
                i1 -= vr * xr
            _add_inner_row(acc, yc, i0, i1, j0, j1, j2)


@jit
def _sums_checked(values, candidates, tint, mask, has_mask, runs, run_label, label, box, ox,
                  oy, cx, cy, ix0, ix1, iy0, iy1, acc):
    """The window sums without masked pixels and pixels of other regions."""
    w = values.shape[1]
    ax0, ay0, ax1, ay1 = box[0], box[1], box[2], box[3]
    first = runs[:, 0] * w + runs[:, 1]  # each run's first pixel: sorted
    for y in range(ay0, ay1 + 1):
        yc = float(y - oy) - cy
        a0 = a1 = a2 = c0 = c1 = c2 = 0.0
        i0 = i1 = j0 = j1 = j2 = 0.0
        inner_row = iy0 <= y <= iy1
        base = y * w
        for x in range(ax0, ax1 + 1):
            if has_mask and mask[y, x]:
                continue
            if candidates[y, x] > tint:  # a region pixel: whose?
                r = np.searchsorted(first, base + x, side="right") - 1
                if run_label[r] != label:
                    continue
            xc = float(x - ox) - cx
            v = float(values[y, x])
            a0 += v
            a1 += v * xc
            a2 += v * (xc * xc)
            c0 += 1.0
            c1 += xc
            c2 += xc * xc
            if inner_row and ix0 <= x <= ix1:
                i0 += v
                i1 += v * xc
                j0 += 1.0
                j1 += xc
                j2 += xc * xc
        _add_row(acc, yc, a0, a1, a2, c0, c1, c2)
        if inner_row:
            _add_inner_row(acc, yc, i0, i1, j0, j1, j2)


@jit
def _add_row(acc, yc, a0, a1, a2, c0, c1, c2):
    """Add one row's window sums (of v and of 1 times 1, x, x^2) to the 2D sums."""
    y2 = yc * yc
    acc[0] += a0
    acc[1] += a1
    acc[2] += a2
    acc[3] += yc * a0
    acc[4] += yc * a1
    acc[5] += y2 * a0
    acc[6] += c0
    acc[7] += c1
    acc[8] += c2
    acc[9] += yc * c0
    acc[10] += yc * c1
    acc[11] += y2 * c0


@jit
def _add_inner_row(acc, yc, i0, i1, j0, j1, j2):
    """Add one row's interior sums (v times 1, x; 1, x, x^2) to the 2D interior sums."""
    acc[12] += i0
    acc[13] += i1
    acc[14] += yc * i0
    acc[15] += j0
    acc[16] += j1
    acc[17] += j2
    acc[18] += yc * j0
    acc[19] += yc * j1
    acc[20] += yc * yc * j0


@jit
def _background_and_moments(s, n, si, ni, level, sigma, out):
    """The reference's ring background (constant, or a plane where it slopes beyond the
    noise) subtracted from the window sums; out: mean x, mean y (about the block centre),
    weight, roundness, background at the centre."""
    r0, rx, ry = s[0] - si[0], s[1] - si[1], s[3] - si[2]
    ring_n = n[0] - ni[0]
    inv_n = 1.0 / max(ring_n, 1.0)
    b0 = r0 * inv_n
    mx_r, my_r = (n[1] - ni[1]) * inv_n, (n[3] - ni[3]) * inv_n
    cxx_r = (n[2] - ni[2]) - (n[1] - ni[1]) * mx_r
    cyy_r = (n[5] - ni[5]) - (n[3] - ni[3]) * my_r
    cxy_r = (n[4] - ni[4]) - (n[1] - ni[1]) * my_r
    gx, gy = rx - r0 * mx_r, ry - r0 * my_r
    det = cxx_r * cyy_r - cxy_r * cxy_r
    ok_det = det > 1e-6 * max(cxx_r * cyy_r, 1e-12)
    if not ok_det:
        det = 1.0
    bx = (cyy_r * gx - cxy_r * gy) / det
    by = (cxx_r * gy - cxy_r * gx) / det
    chi2 = bx * gx + by * gy
    if ok_det and ring_n >= 8 and chi2 > _SLOPE_CHI2 * sigma * sigma:
        b0 = b0 - bx * mx_r - by * my_r
    else:
        bx = by = 0.0
    if not ring_n > 0:  # the window fills the image: the image's background level
        b0 = level
    t0 = s[0] - b0 * n[0] - (bx * n[1] + by * n[3])
    t1 = s[1] - b0 * n[1] - (bx * n[2] + by * n[4])
    t3 = s[3] - b0 * n[3] - (bx * n[4] + by * n[5])
    t2 = s[2] - b0 * n[2]
    t4 = s[4] - b0 * n[4]
    t6 = s[5] - b0 * n[5]
    good = t0 > 0
    d = t0 if good else 1.0
    mean_x, mean_y = t1 / d, t3 / d
    cxx = max(t2 / d - mean_x * mean_x, 0.0) + 1.0 / 12.0
    cyy = max(t6 / d - mean_y * mean_y, 0.0) + 1.0 / 12.0
    cxy = t4 / d - mean_x * mean_y
    half_tr = 0.5 * (cxx + cyy)
    disc = np.sqrt(0.25 * (cxx - cyy) ** 2 + cxy * cxy)
    out[0] = mean_x
    out[1] = mean_y
    out[2] = t0 if good else 0.0
    out[3] = np.sqrt(max(half_tr - disc, 0.0) / (half_tr + disc))
    out[4] = b0
