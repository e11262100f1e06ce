"""A take's C3D bytes with its point frames written in one block, not one frame at a time.

Why: the c3d library's writer converts and writes each frame with a handful of numpy calls
(and takes the frames as a list of per-frame arrays), which is a tenth of `mocapd label`'s
whole CPU time on a 2751-frame take. Here the library still writes the header and the
parameters (the format's fiddly part); only the data section is written here, as one
float32 array, with exactly the bytes the library writes frame by frame (tested against
it), so every reader sees the same file as before.
"""

from __future__ import annotations

import io
import warnings
from typing import TYPE_CHECKING

import c3d
import numpy as np

if TYPE_CHECKING:  # c3dio imports this module to write: the type only, no cycle
    from daemon.formats.c3dio import Take


def c3d_bytes(take: Take) -> bytes:
    """The take as a float C3D in millimetres: measured samples with residual 1, filled ones
    0 (the C3D convention for interpolated samples), missing ones -1."""
    mm = take.xyz_m * 1000.0
    seen = np.isfinite(mm).all(axis=2)                                  # (F, n)
    pts = np.zeros(mm.shape[:2] + (5,), dtype=np.float32)
    pts[..., :3] = np.where(seen[..., None], mm, 0.0)
    pts[..., 3] = np.where(seen, np.where(take.filled, 0.0, 1.0), -1.0)
    pts[..., 4] = np.where(seen, 0.0, -1.0)
    writer = _BlockWriter(pts, point_rate=float(take.rate_hz), analog_rate=0.0,
                          point_scale=-1.0)
    writer.set_point_labels(take.labels)
    writer.set_start_frame(max(int(take.first_frame), 1))
    buf = io.BytesIO()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        writer.write(buf)
    return buf.getvalue()


class _BlockWriter(c3d.Writer):
    """c3d.Writer whose data section is written from one (frames, points, 5) float32 array
    (x, y, z, residual, camera word: the library's per-frame layout) in one go."""

    def __init__(self, points: np.ndarray, **kwargs) -> None:
        super().__init__(**kwargs)
        self._block = points
        no_analog = np.zeros((0, 0), dtype=np.float32)
        # the library's metadata (point count, frame count) is taken from its frame list
        self.add_frames([(p, no_analog) for p in points])

    def _write_frames(self, handle) -> None:
        """The library's float layout (c3d 0.5-0.6, Writer._write_frames): x, y, z as
        float32 and a fourth word holding residual | camera << 8, -1 for a missing
        sample. The library reuses one frame buffer, so a missing sample's x, y, z are
        those of the marker's last sample written before it (0 before any): kept, so the
        bytes are the library's."""
        assert handle.tell() == 512 * (int(self._header.data_block) - 1)
        if self.point_scale >= 0:                  # integer C3D: the library's own loop
            super()._write_frames(handle)
            return
        pts = self._block
        n_frames, n = pts.shape[:2]
        valid = pts[..., 3] >= 0.0
        # the last frame at or before each one where the marker was valid (-1: none)
        last = np.where(valid, np.arange(n_frames)[:, None], -1)
        np.maximum.accumulate(last, axis=0, out=last)
        raw = np.zeros((n_frames, n, 4), dtype=self._dtypes.float32)
        has = last >= 0
        f_idx, m_idx = np.nonzero(has)
        raw[f_idx, m_idx, :3] = pts[last[f_idx, m_idx], m_idx, :3]
        res = np.where(valid, pts[..., 3], 0.0)
        cam = np.where(valid, pts[..., 4], 0.0)
        word = np.bitwise_or(np.rint(res / abs(self.point_scale)).astype(np.uint8),
                             cam.astype(np.uint16) << 8, dtype=np.uint16)
        raw[..., 3] = np.where(valid, word.astype(np.float32), np.float32(-1.0))
        handle.write(raw.tobytes())
        self._pad_block(handle)
