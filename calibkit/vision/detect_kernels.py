"""Compiled (numba) kernels for marker detection's hot path: background and regions (the
windowed moments are in calibkit.vision.detect_moments_kernels; `measure` is named here too).

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
from calibkit.vision.detect_moments_kernels import measure  # noqa: F401 (detect's entry)

_CHUNK = 64  # pixels tested at once for "any pixel above the threshold" (one SIMD reduction)


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
