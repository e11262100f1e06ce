"""Connected regions of a sparse set of bright pixels, without labelling the whole image.

OpenCV's labeller with statistics costs milliseconds per VGA frame; markers are sparse, so
the pixels above the threshold are gathered once, joined into horizontal runs, the runs
are linked to overlapping runs in the row above (8-connectivity), and the run forest is
collapsed by pointer jumping. The numpy code here is the reference; the compiled kernels
(calibkit.vision.detect_kernels) give the same regions.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from calibkit.vision.detect_config import jit_kernels


def label_pixels(pix: np.ndarray, width: int) -> tuple[np.ndarray, int]:
    """8-connected regions of the pixels with sorted flat indices `pix` -> (label per pixel, n).

    Labels are numbered in raster order of each region's first pixel.
    """
    return label_pixels_with(pix, width, jit_kernels())


def label_pixels_with(pix: np.ndarray, width: int, kernels) -> tuple[np.ndarray, int]:
    """label_pixels with the compiled kernels given (None: in numpy)."""
    if kernels is not None:
        return kernels.label_sorted(np.asarray(pix, dtype=np.int64), int(width))
    runs = Runs.find(pix, width)
    return runs.pixel_labels(), runs.n


@dataclass
class Runs:
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
    def find(cls, pix: np.ndarray, width: int) -> Runs:
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

    def regions(self, image: np.ndarray) -> Regions:
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
        return Regions(area, bbox.T, peak, self.pix, self.pixel_labels)


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
class Regions:
    """Regions to measure: per region area, bbox (x0 y0 x1 y1), peak; and their pixels."""

    area: np.ndarray
    bbox: np.ndarray
    peak: np.ndarray
    pix: np.ndarray  # flat indices of all region pixels
    labels: Callable[[], np.ndarray]  # region of each of pix, computed when needed

    @classmethod
    def from_pixels(cls, image: np.ndarray, pix: np.ndarray, labels: np.ndarray,
                    n: int) -> Regions:
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
