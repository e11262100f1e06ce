"""Tracking a points CSV of any length in bounded memory: spooled, then tracked a window at a time.

Why: an hour of capture is a gigabyte of points CSV. Packed whole (every frame's markers in
one array, every frame's tracks, every pose), tracking it took several times the file in
memory. Here the file is parsed once (daemon.formats.points_csv, a block at a time) into a
spool: an unnamed temporary file of 32-byte records (frame, x, y, z) in the file's order,
with the first record of each frame indexed. Windows of whole frames (at most
`window_points` points, or a single frame) are then read back, tracked by one CloudTracker
that carries the point tracks and the bodies from window to window, and their poses
written to the output as they come. What stays in memory is one window, the index
(16 bytes a frame) and the arrays the figures are made of (13 bytes a frame and body),
not the file.

The definitions are fitted to the take (daemon.analysis.body_refine) before tracking, and a
body never found gets its hint after; both look at a few hundred frames spread over the
whole take, read from the spool when asked (SpooledFrames), so they see what they see in
a run on the whole take. The result is that run's, pose for pose
(tests/test_track_windows.py checks it, with window edges inside occlusions).

The spool is 32 bytes a point where the text is 30-50: it goes in the output's folder
(the user chose to write there) and is gone when the run ends, however it ends. A file
whose frame numbers go back somewhere cannot be cut into windows of whole frames:
`Spool.ordered` says so, and the caller tracks it whole, as before.
"""

from __future__ import annotations

import os
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from calibkit.core.fileio import atomic_write
from daemon.analysis.body_refine import refine_bodies
from daemon.analysis.offline_track import CloudTracker, PoseFigures, cloud_from_points, figures_of
from daemon.analysis.point_tracks import PointTrackConfig
from daemon.analysis.track_file import add_hints, pose_table
from daemon.formats.c3dio import Points
from daemon.formats.trajectory_io import POSES_COLUMNS, write_poses_rows
from daemon.tracking.rigid import BodyDef, RigidConfig

RECORD = np.dtype([("frame", "<i8"), ("xyz", "<f8", (3,))])
WINDOW_POINTS = 1 << 19  # points tracked at once: ~0.1 GB of working arrays, and numpy
# and the kernels still work on long runs of frames (thousands at 45 points a frame)


class Spool:
    """A points CSV's usable points on disk, frame numbers indexed: the sink
    points_csv.stream_points_csv fills (`put`), then read back by frame rows."""

    def __init__(self, folder: str | Path | None = None) -> None:
        self.file = tempfile.TemporaryFile(prefix="mocapd-track-", suffix=".spool",
                                           dir=folder)  # unlinked at once: never left over
        self.n = 0  # points
        self.ordered = True  # frame numbers never go back
        self._frames: list[np.ndarray] = []
        self._starts: list[np.ndarray] = []
        self._last: int | None = None
        self.frames = np.zeros(0, np.int64)  # (F,) the frames with points, in file order
        self.starts = np.zeros(1, np.int64)  # (F + 1,) frame row f's points: starts[f:f+2]

    def put(self, frame: np.ndarray, xyz: np.ndarray) -> None:
        rec = np.empty(len(frame), RECORD)
        rec["frame"], rec["xyz"] = frame, xyz
        self.file.write(rec.tobytes())
        new = np.ones(len(frame), dtype=bool)
        new[1:] = frame[1:] != frame[:-1]
        if self._last is not None:
            new[0] = frame[0] != self._last
            self.ordered &= bool(frame[0] >= self._last)
        self.ordered &= not bool(np.any(np.diff(frame) < 0))
        self._frames.append(frame[new])
        self._starts.append(self.n + np.flatnonzero(new))
        self._last = int(frame[-1])
        self.n += len(frame)

    def finish(self) -> Spool:
        """Called once every point is in: the index is built, the file readable."""
        self.file.flush()
        self.frames = np.concatenate(self._frames) if self._frames else np.zeros(0, np.int64)
        self.starts = np.append(np.concatenate(self._starts) if self._starts
                                else np.zeros(0, np.int64), self.n).astype(np.int64)
        self._frames, self._starts = [], []
        return self

    def rows(self, a: int, b: int) -> tuple[np.ndarray, np.ndarray]:
        """(frame (n,), xyz (n, 3)) of points a..b-1, in the file's order."""
        raw = os.pread(self.file.fileno(), (b - a) * RECORD.itemsize, a * RECORD.itemsize)
        rec = np.frombuffer(raw, RECORD)
        return rec["frame"].copy(), rec["xyz"].copy()

    def points(self) -> Points:
        """Every point (for a file that cannot be tracked in windows)."""
        return Points(*self.rows(0, self.n))

    def close(self) -> None:
        self.file.close()

    def __enter__(self) -> Spool:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class SpooledFrames:
    """The take's frames as body_refine looks at a NaN-padded (F, P, 3) array: its length,
    and frame row f's points (turned by `turn`, 3x3, if given), read when asked."""

    def __init__(self, spool: Spool, turn: np.ndarray | None = None) -> None:
        self.spool, self.turn = spool, turn

    def __len__(self) -> int:
        return len(self.spool.frames)

    def __getitem__(self, f) -> np.ndarray:
        s = self.spool.starts
        xyz = self.spool.rows(int(s[f]), int(s[f + 1]))[1]
        return xyz if self.turn is None else xyz @ self.turn.T


def windows(starts: np.ndarray, most: int):
    """(first, end) frame rows of consecutive windows of whole frames, each holding at most
    `most` points (or a single frame that holds more)."""
    n_frames = len(starts) - 1
    k = 0
    while k < n_frames:
        end = int(np.searchsorted(starts, starts[k] + most, side="right")) - 1
        end = min(max(end, k + 1), n_frames)
        yield k, end
        k = end


def track_spool(spool: Spool, rate_hz: float, defs: list[BodyDef], rigid_cfg: RigidConfig,
                gate_mm: float, gross_mm: float, out: Path, comment: str, progress=None,
                refine: str = "auto", turn: np.ndarray | None = None,
                window_points: int | None = None) -> tuple[dict, list[BodyDef]]:
    """track_file's run on a spooled points CSV, a window at a time, the poses written to
    the poses CSV `out` as they come (whole or not at all): (figures, the definitions the
    poses were made with). `turn` (3x3) turns the points into mocapd's z-up world;
    window_points defaults to WINDOW_POINTS."""
    if not spool.ordered:
        raise ValueError("a spool whose frames go back cannot be tracked in windows")
    start = time.perf_counter()
    frames = SpooledFrames(spool, turn)
    used, refits = refine_bodies(frames, list(defs), rigid_cfg.distance_tol_m, refine)
    tracker = CloudTracker(used, replace(rigid_cfg, refine=False),
                           PointTrackConfig(gate_m=gate_mm / 1000.0))
    n, nb = len(frames), len(used)
    kept = PoseFigures([b.name for b in used], np.array([b.id for b in used], np.int64),
                       np.zeros((n, nb), bool), np.full((n, nb), np.nan),
                       np.zeros((n, nb), np.int32), np.zeros(n, np.int64))  # filled in place
    count = 0
    with atomic_write(out, "w", newline="", encoding="utf-8") as handle:
        handle.write(f"# {comment}\n" + ",".join(POSES_COLUMNS) + "\n")
        for a, b in windows(spool.starts, window_points or WINDOW_POINTS):
            frame, xyz = spool.rows(int(spool.starts[a]), int(spool.starts[b]))
            if turn is not None:
                xyz = xyz @ turn.T
            result = tracker.window(cloud_from_points(Points(frame, xyz), rate_hz), progress)
            write_poses_rows(handle, pose_table(result))
            kept.valid[a:b], kept.error_m[a:b] = result.valid, result.error_m
            kept.n_markers[a:b], kept.markers_seen[a:b] = result.n_markers, result.markers_seen
            count += 1
    elapsed = time.perf_counter() - start
    figs = figures_of(kept, gross_mm)
    figs["frames_per_s"] = n / elapsed if elapsed > 0 else None
    figs["windows"] = count
    add_hints(figs, frames, defs, used, refits, rigid_cfg.distance_tol_m)
    return figs, used
