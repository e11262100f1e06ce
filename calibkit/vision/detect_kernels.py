"""Compiled (numba) kernels for marker detection's hot path: regions and windowed moments.

Why: a VGA frame with 40 markers is ~300 k pixel comparisons and ~7 k window pixels of
arithmetic, a few tens of microseconds of work; as numpy array operations the time went to
the overheads of ~80 small calls instead. These kernels do the same sums in one pass each.
The numpy implementation in calibkit.vision.detect stays as the reference (detect_reference): the
tests check that both give the same blobs, so any change here is checked against it. They
agree exactly, not just closely: pixel values are integers and window coordinates
half-integers, so every sum is exact in any order.

Caching: compiled code is cached in NUMBA_CACHE_DIR if set, else beside this module, else
in numba's user cache directory; where none can be written (a read-only install run by a
user without a home, as a service may be) the kernels are compiled in memory instead.

Note for changes: LLVM vectorises the fixed-length max loop of chunk_maxima only in the
form written there (indexing by k * _CHUNK made it 15x slower); bench_detect.py shows it.
"""

from __future__ import annotations

import numpy as np

from calibkit.core.jit import jit

_CHUNK = 64  # pixels tested at once for "any pixel above the threshold" (one SIMD reduction)
# as calibkit.vision.detect_centroids: chi-square (2 dof, p = 0.001) for a sloping ring
_SLOPE_CHI2 = 13.8


# ---------------------------------------------------------------------------------------------
# Background level


@jit
def background_u8(image, mask, has_mask, sy, sx):
    """(level, noise sigma) of an 8-bit image: calibkit.vision.detect.background_level's estimate.

    The same sparse grid of horizontally adjacent pixel pairs, the same histogram of values
    and of differences, the same quantiles interpolated within integer bins.
    """
    h, w = image.shape
    hist = np.zeros(767, dtype=np.int64)  # values 0..255, then differences + 511: 256..766
    m = 0
    for y in range(0, h, sy):
        for x in range(0, w - 1, sx):
            if has_mask and (mask[y, x] or mask[y, x + 1]):
                continue
            a = np.int64(image[y, x])
            hist[a] += 1
            hist[a - np.int64(image[y, x + 1]) + 511] += 1
            m += 1
    if m == 0:
        return 0.0, 0.0
    n_val = float(m)
    level = _quantile(hist, 0.5 * n_val)
    q25 = _quantile(hist, n_val + 0.25 * m) - 256
    q75 = _quantile(hist, n_val + 0.75 * m) - 256
    return level, (q75 - q25) / (1.349 * np.sqrt(2.0))


@jit
def _quantile(hist, target):
    """The histogram's value at cumulative count `target`, interpolated within its bin."""
    below = 0
    for k in range(len(hist)):
        cdf = below + hist[k]
        if cdf >= target:
            return k - 0.5 + (target - below) / max(hist[k], 1)
        below = cdf
    return len(hist) - 0.5


# ---------------------------------------------------------------------------------------------
# Runs and regions


@jit
def find_regions(image, tint, values, mask, has_mask, hot, capacity):
    """8-connected regions of the pixels above `tint` (not masked), from horizontal runs.

    Only the chunks `hot` (from chunk_maxima and hot_chunks, of the image as one flat
    array: those holding a pixel above the threshold) are visited pixel by pixel: markers
    are sparse. Each run is linked to the touching runs of the row above as it closes
    (union-find, the smaller run index is the root), so a region's number is the raster
    order of its first pixel, as in the numpy reference.

    Returns the runs (rows of y, x0, x1, peak, parent) with the region of each, per region
    the area, bbox (x0, y0, x1, y1) and the peak of `values`; and False (with nothing else
    done) if more than `capacity` runs might be needed: call again with max_runs(...).
    """
    h, w = image.shape
    flat = image.reshape(-1)
    vflat = values.reshape(-1)
    mflat = mask.reshape(-1)
    size = h * w
    per_chunk = _runs_per_chunk(w)
    runs = np.empty((capacity, 5), dtype=np.int64)
    rows = np.array([-2, 0, 0, 0])  # row of the last run, first run of it, of the row above, p
    n = 0
    open_run = False
    start = row_end = pk = 0
    chunk_end = 0
    for c in hot:
        if n + per_chunk + 1 > capacity:
            return runs[:0], runs[:0, 0], np.zeros(0), runs[:0, :4], np.zeros(0), False
        if open_run and c != chunk_end:  # the run reached the end of the previous hot chunk
            open_run = False
            _push(runs, n, start, chunk_end - 1, w, pk, rows)
            n += 1
        chunk_end = min(c + _CHUNK, size)
        i = c - 1
        while i + 1 < chunk_end:
            i += 1
            if not open_run:  # skip the background up to the next candidate quickly
                while i < chunk_end and not flat[i] > tint:
                    i += 1
                if i == chunk_end:
                    break
            elif i == row_end:
                open_run = False
                _push(runs, n, start, i - 1, w, pk, rows)
                n += 1
            if flat[i] > tint and not (has_mask and mflat[i]):
                v = np.int64(vflat[i])
                if open_run:
                    pk = max(pk, v)
                else:
                    open_run = True
                    start = i
                    row_end = (i // w + 1) * w
                    pk = v
            elif open_run:
                open_run = False
                _push(runs, n, start, i - 1, w, pk, rows)
                n += 1
    if open_run:
        _push(runs, n, start, chunk_end - 1, w, pk, rows)
        n += 1
    runs = runs[:n]
    run_label, area, bbox, peak = _region_stats(runs)
    return runs, run_label, area, bbox, peak, True


@jit
def _runs_per_chunk(w):
    """Runs starting in a chunk: at most one per two pixels, plus one per row start in it."""
    return _CHUNK // 2 + _CHUNK // w + 2


@jit
def max_runs(n_hot, w):
    """The most runs `n_hot` hot chunks of an image `w` pixels wide can hold."""
    return n_hot * _runs_per_chunk(w) + 1


@jit
def chunk_maxima(flat):
    """The largest value of each chunk of `flat` (the last chunk may be short).

    A fixed-size chunk's maximum compiles to a few SIMD instructions, so a VGA frame costs a
    few microseconds, most of it reading the frame from memory; the background estimate
    that follows then finds the frame in the cache. (Chunks under 64 pixels did not
    vectorise, and inside a bigger loop the reduction compiled to slow code in some builds:
    it stays on its own.)
    """
    size = len(flat)
    full = size // _CHUNK
    out = np.empty(full + (1 if size % _CHUNK else 0), dtype=flat.dtype)
    k = 0
    for c in range(0, size - _CHUNK + 1, _CHUNK):  # (indexing by k * _CHUNK: 15x slower)
        top = flat[c]
        for i in range(_CHUNK):
            v = flat[c + i]
            top = v if v > top else top
        out[k] = top
        k += 1
    if size % _CHUNK:
        top = flat[full * _CHUNK]
        for i in range(full * _CHUNK, size):
            v = flat[i]
            top = v if v > top else top
        out[full] = top
    return out


@jit
def hot_chunks(maxima, tint):
    """Starts (flat pixel indices) of the chunks whose maximum is above `tint`."""
    hot = np.empty(len(maxima), dtype=np.int64)
    k = 0
    for j in range(len(maxima)):
        if maxima[j] > tint:
            hot[k] = j * _CHUNK
            k += 1
    return hot[:k]


@jit
def label_sorted(pix, w):
    """8-connected regions of the pixels with sorted flat indices `pix` in an image `w`
    wide -> (region of each pixel, number of regions), numbered in raster order of each
    region's first pixel: calibkit.vision.detect.label_pixels."""
    runs = np.empty((len(pix), 5), dtype=np.int64)  # at most one run per pixel
    rows = np.array([-2, 0, 0, 0])
    n = 0
    i = 0
    while i < len(pix):
        row_end = (pix[i] // w + 1) * w
        j = i + 1
        while j < len(pix) and pix[j] == pix[j - 1] + 1 and pix[j] < row_end:
            j += 1
        _push(runs, n, pix[i], pix[j - 1], w, 0, rows)
        n += 1
        i = j
    runs = runs[:n]
    run_label, area, _, _ = _region_stats(runs)
    labels = np.empty(len(pix), dtype=np.int64)
    k = 0
    for r in range(n):
        for _ in range(runs[r, 2] - runs[r, 1] + 1):
            labels[k] = run_label[r]
            k += 1
    return labels, len(area)


@jit
def _push(runs, n, first, last, w, pk, rows):
    """Store run n (flat pixel indices first..last of one row) and join it to the runs of
    the row above that it touches (8-connectivity: columns x0 - 1 .. x1 + 1). `rows`
    carries the row bookkeeping between calls: the row of the previous run, the first run
    of that row, the first run of the row above it, and the first run of the row above
    that can still touch a run (runs of the row above that end left of this run cannot
    touch later runs of this row either)."""
    y = first // w
    x0 = first - y * w
    x1 = last - y * w
    if y != rows[0]:
        rows[2] = rows[1] if y == rows[0] + 1 else n  # no runs in the row above: empty
        rows[1] = n
        rows[0] = y
        rows[3] = rows[2]
    row_lo = rows[1]
    p = rows[3]
    runs[n, 0] = y
    runs[n, 1] = x0
    runs[n, 2] = x1
    runs[n, 3] = pk
    runs[n, 4] = n
    parent = runs[:, 4]
    while p < row_lo and runs[p, 2] < x0 - 1:
        p += 1
    rows[3] = p
    q = p
    while q < row_lo and runs[q, 1] <= x1 + 1:
        a = _root(parent, n)
        b = _root(parent, q)
        if a < b:
            parent[b] = a
        elif b < a:
            parent[a] = b
        q += 1


@jit
def _root(parent, i):
    while parent[i] != i:
        parent[i] = parent[parent[i]]  # path halving
        i = parent[i]
    return i


@jit
def _region_stats(runs):
    """Region of each run (numbered by first run) and per region area, bbox and peak."""
    n = len(runs)
    parent = runs[:, 4]
    run_label = np.empty(n, dtype=np.int64)
    nreg = 0
    for r in range(n):
        root = _root(parent, r)
        if root == r:
            run_label[r] = nreg
            nreg += 1
        else:
            run_label[r] = run_label[root]
    area = np.zeros(nreg, dtype=np.float64)
    bbox = np.empty((nreg, 4), dtype=np.int64)
    peak = np.zeros(nreg, dtype=np.float64)
    bbox[:, :2] = np.iinfo(np.int64).max
    bbox[:, 2:] = -1
    for r in range(n):
        k = run_label[r]
        y, x0, x1 = runs[r, 0], runs[r, 1], runs[r, 2]
        area[k] += x1 - x0 + 1
        bbox[k, 0] = min(bbox[k, 0], x0)
        bbox[k, 1] = min(bbox[k, 1], y)
        bbox[k, 2] = max(bbox[k, 2], x1)
        bbox[k, 3] = max(bbox[k, 3], y)
        peak[k] = max(peak[k], float(runs[r, 3]))
    return run_label, area, bbox, peak


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
