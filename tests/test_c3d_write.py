"""The C3D writer that writes the frames in one block gives the c3d library's own bytes and
reads back as the take it was given."""

from __future__ import annotations

import io
import warnings

import c3d
import numpy as np

from daemon.formats.c3d_write import c3d_bytes
from daemon.formats.c3dio import Take, read_c3d, write_c3d


def _library_bytes(take: Take) -> bytes:
    """The take written by the c3d library frame by frame (write_c3d before the block
    writer): the reference."""
    writer = c3d.Writer(point_rate=float(take.rate_hz), analog_rate=0.0, point_scale=-1.0)
    writer.set_point_labels(take.labels)
    writer.set_start_frame(max(int(take.first_frame), 1))
    n = len(take.labels)
    no_analog = np.zeros((0, 0), dtype=np.float32)
    mm = take.xyz_m * 1000.0
    frames = []
    for f in range(take.n_frames):
        pts = np.zeros((n, 5), dtype=np.float32)
        ok = np.isfinite(mm[f]).all(axis=1)
        pts[ok, :3] = mm[f, ok]
        pts[ok, 3] = np.where(take.filled[f, ok], 0.0, 1.0)
        pts[~ok, 3] = -1.0
        pts[~ok, 4] = -1.0
        frames.append((pts, no_analog))
    writer.add_frames(frames)
    buf = io.BytesIO()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        writer.write(buf)
    return buf.getvalue()


def _take(seed: int, frames: int = 137, markers: int = 7) -> Take:
    """Markers wandering about, with gaps (one marker never seen until late, one missing
    in the first frame) and filled samples."""
    rng = np.random.default_rng(seed)
    xyz = rng.normal(0.0, 0.5, (frames, markers, 3)).cumsum(0) * 0.01
    xyz[:40, 2] = np.nan                       # not seen until frame 40
    xyz[0, 0] = np.nan
    xyz[rng.random((frames, markers)) < 0.1] = np.nan
    filled = np.isfinite(xyz).all(2) & (rng.random((frames, markers)) < 0.1)
    return Take([f"M{k}" for k in range(markers)], xyz, 100.0, first_frame=12,
                filled=filled)


def test_block_writer_gives_the_library_bytes():
    for seed in range(3):
        take = _take(seed)
        assert c3d_bytes(take) == _library_bytes(take)


def test_block_writer_reads_back(tmp_path):
    take = _take(5)
    path = tmp_path / "t.c3d"
    write_c3d(path, take)
    back = read_c3d(path)
    assert back.labels == take.labels
    assert back.n_frames == take.n_frames
    assert back.rate_hz == take.rate_hz
    np.testing.assert_array_equal(np.isnan(back.xyz_m), np.isnan(take.xyz_m))
    seen = np.isfinite(take.xyz_m)
    np.testing.assert_allclose(back.xyz_m[seen], take.xyz_m[seen], atol=1e-6)
    np.testing.assert_array_equal(back.filled, take.filled)
