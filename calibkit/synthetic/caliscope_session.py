"""A real caliscope ChArUco session as a correspondence benchmark: its corners split into what
the estimate gets and what only the scorer reads, and the scorer.

Why here: a real board's corner ids are ground truth in the same sense as the simulator's
marker ids. The estimate gets each camera's corners as unlabelled blobs (frame, camera,
capture time, pixels), as markers would give them; the ids and the corners' places on the
board stay in the `Session` for `score_board` alone, which lives with the other scorers so
that no estimating code can import it (tests/test_boundary.py).

caliscope's files (mprib/caliscope; the columns read by name, in any order):
- `camera_array.toml`: the cameras, read by `calibkit.core.rigformats.caliscope`;
- `calibration/extrinsic/xy.csv`: one row per detected corner: `sync_index` (caliscope's
  set of frames taken as one instant), `cam_id`, `frame_time` (seconds), `object_id`,
  `keypoint_id`, `img_loc_x`, `img_loc_y` (pixels), `obj_loc_x`, `obj_loc_y` (the corner on
  the board, metres);
- `calibration/extrinsic/stereotriangulated_points.csv`: caliscope's own points, one per
  camera pair and corner (`pair`, `sync_index`, `object_id`, `keypoint_id`, `x_pos`,
  `y_pos`, `z_pos`).
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from calibkit.core.camera import Rig
from calibkit.core.errors import UserError
from calibkit.core.geometry import RigArrays, triangulate
from calibkit.core.observations import Observations
from calibkit.core.rigformats.caliscope import read_caliscope

XY_COLUMNS = ("sync_index", "cam_id", "frame_time", "object_id", "keypoint_id", "img_loc_x",
              "img_loc_y", "obj_loc_x", "obj_loc_y")
POINT_COLUMNS = ("sync_index", "object_id", "keypoint_id", "x_pos", "y_pos", "z_pos")
_ID_SPAN = 1 << 20  # corner key = object_id * _ID_SPAN + keypoint_id


def _columns(path: Path, names: tuple[str, ...]) -> dict[str, np.ndarray]:
    """The named columns of a CSV file as float arrays; a UserError for a missing file,
    column or a value that is not a number."""
    try:
        with open(path, newline="", encoding="utf-8") as handle:
            reader = csv.reader(handle)
            header = next(reader, None)
            rows = list(reader)
    except OSError as exc:
        raise UserError(f"{path}: cannot be read ({exc.strerror})") from None
    if header is None:
        raise UserError(f"{path}: is empty")
    header = [h.strip() for h in header]
    missing = [n for n in names if n not in header]
    if missing:
        raise UserError(f"{path}: has no column {', '.join(missing)}")
    out = {}
    for name in names:
        k = header.index(name)
        try:
            out[name] = np.array([float(r[k]) for r in rows if r], dtype=np.float64)
        except (ValueError, IndexError):
            raise UserError(f"{path}: column {name} holds a value that is not a number") \
                from None
        if not np.all(np.isfinite(out[name])):
            raise UserError(f"{path}: column {name} holds a value that is not finite")
    return out


@dataclass(eq=False)
class Session:
    """The estimate's input (`rig`, `obs`) and the scorer's truth (`corner`, `board_xy`)."""

    folder: Path
    rig: Rig
    obs: Observations  # unlabelled: no ids in it
    corner: np.ndarray  # (N,) int64 corner key of each blob (object and keypoint id)
    board_xy: np.ndarray  # (N, 2) metres, the corner's place on its board

    def square_m(self) -> float:
        """The board's square: the smallest distance between two corners of the board."""
        keys, first = np.unique(self.corner, return_index=True)
        xy = self.board_xy[first]
        d = np.linalg.norm(xy[:, None] - xy[None], axis=2)
        same_board = (keys[:, None] // _ID_SPAN) == (keys[None] // _ID_SPAN)
        d = d[same_board & (d > 1e-9)]
        if not len(d):
            raise UserError(f"{self.folder}: the corners give no board square")
        return float(d.min())


def load_session(folder: str | Path) -> Session:
    """A caliscope session folder: its rig and its extrinsic recording's corners."""
    folder = Path(folder)
    rig = read_caliscope(folder / "camera_array.toml")
    xy = _columns(folder / "calibration" / "extrinsic" / "xy.csv", XY_COLUMNS)
    if not len(xy["cam_id"]):
        raise UserError(f"{folder}: xy.csv holds no corners")
    index = {name: i for i, name in enumerate(rig.names)}
    names = [f"cam_{int(c)}" for c in xy["cam_id"]]
    unknown = sorted({n for n in names if n not in index})
    if unknown:
        raise UserError(f"{folder}: xy.csv has corners of {', '.join(unknown)}, which "
                        "camera_array.toml does not calibrate")
    camera = np.array([index[n] for n in names], dtype=np.int32)
    n = len(camera)
    obs = Observations(tuple(rig.names), tuple(c.size for c in rig),
                       xy["sync_index"].astype(np.int64), camera,
                       np.round(xy["frame_time"] * 1e9).astype(np.int64),
                       np.stack([xy["img_loc_x"], xy["img_loc_y"]], axis=1),
                       np.ones(n), np.ones(n), meta={"source": "caliscope xy.csv"})
    corner = xy["object_id"].astype(np.int64) * _ID_SPAN + xy["keypoint_id"].astype(np.int64)
    return Session(folder, rig, obs, corner, np.stack([xy["obj_loc_x"], xy["obj_loc_y"]], 1))


@dataclass(frozen=True)
class BoardScore:
    """Triangulated points against the board: the issue-28 figures."""

    corners_seen_3: int  # (frame, corner) seen by >= 3 cameras
    recovered_3: int  # of those, how many some point stands for
    points: int
    ghosts: int  # points whose blobs belong to more than one corner
    spacing_pairs: int  # adjacent corners both found in one frame
    spacing_mm_rms: float  # RMS of (3D distance - square), over those pairs
    spacing_mm_mean: float
    lost: tuple[tuple[int, int], ...]  # (frame, corner key) seen by >= 3 and not found

    @property
    def recovered_fraction(self) -> float:
        return self.recovered_3 / self.corners_seen_3 if self.corners_seen_3 else float("nan")

    @property
    def ghost_fraction(self) -> float:
        return self.ghosts / self.points if self.points else 0.0

    def as_dict(self) -> dict:
        return {"corners_seen_3": self.corners_seen_3, "recovered_3": self.recovered_3,
                "recovered_fraction": self.recovered_fraction, "points": self.points,
                "ghosts": self.ghosts, "ghost_fraction": self.ghost_fraction,
                "spacing_pairs": self.spacing_pairs, "spacing_mm_rms": self.spacing_mm_rms,
                "spacing_mm_mean": self.spacing_mm_mean, "lost": len(self.lost)}


def _spacing(frame: np.ndarray, corner: np.ndarray, xyz: np.ndarray, board: dict[int, tuple],
             square_m: float) -> np.ndarray:
    """3D distance minus the square (m) for every pair of board-adjacent corners of a frame."""
    order = np.lexsort((corner, frame))
    frame, corner, xyz = frame[order], corner[order], xyz[order]
    starts = np.flatnonzero(np.r_[True, frame[1:] != frame[:-1]])
    ends = np.r_[starts[1:], len(frame)]
    out = []
    for a, b in zip(starts, ends, strict=True):  # per frame: a dozen corners
        keys = corner[a:b]
        xy = np.array([board[int(k)] for k in keys])
        d_board = np.linalg.norm(xy[:, None] - xy[None], axis=2)
        same = (keys[:, None] // _ID_SPAN) == (keys[None] // _ID_SPAN)
        i, j = np.nonzero(np.triu(same & (np.abs(d_board - square_m) < 1e-3 * square_m), 1))
        out.append(np.linalg.norm(xyz[a:b][i] - xyz[a:b][j], axis=1) - square_m)
    return np.concatenate(out) if out else np.zeros(0)


def score_board(session: Session, frame: np.ndarray, rows: np.ndarray,
                xyz: np.ndarray) -> BoardScore:
    """Score points (frame (P,), rows (P, C) of `session.obs` each used or -1, xyz (P, 3))
    with the corner ids: a point stands for a corner when all its blobs carry that corner's
    id, and is a ghost otherwise."""
    obs = session.obs
    key = obs.frame * (_ID_SPAN * 64) + session.corner
    seen_keys, seen_count = np.unique(key, return_counts=True)
    wanted = seen_keys[seen_count >= 3]
    used = rows >= 0
    ids = np.where(used, session.corner[np.maximum(rows, 0)], -1)
    lo = np.where(used, ids, np.iinfo(np.int64).max).min(axis=1)
    hi = ids.max(axis=1)
    good = used.any(axis=1) & (lo == hi)
    point_key = np.asarray(frame, dtype=np.int64) * (_ID_SPAN * 64) + hi
    found = np.isin(wanted, point_key[good])
    board = {int(k): tuple(v) for k, v in zip(session.corner, session.board_xy, strict=True)}
    d = _spacing(np.asarray(frame)[good], hi[good], xyz[good], board, session.square_m())
    lost = tuple((int(k // (_ID_SPAN * 64)), int(k % (_ID_SPAN * 64))) for k in wanted[~found])
    return BoardScore(len(wanted), int(found.sum()), len(frame), int((~good).sum()), len(d),
                      float(np.sqrt(np.mean(d**2)) * 1e3) if len(d) else float("nan"),
                      float(np.mean(d) * 1e3) if len(d) else float("nan"), lost)


def caliscope_spacing(session: Session, only: set[tuple[int, int, int]] | None = None
                      ) -> tuple[int, float, float]:
    """caliscope's own adjacent-corner spacing (pairs, RMS mm, mean mm) from its
    stereotriangulated points, each corner the mean of its camera pairs' points; `only`
    keeps the (frame, corner, corner) pairs given (to compare on the same pairs)."""
    path = session.folder / "calibration" / "extrinsic" / "stereotriangulated_points.csv"
    cols = _columns(path, POINT_COLUMNS)
    frame = cols["sync_index"].astype(np.int64)
    corner = cols["object_id"].astype(np.int64) * _ID_SPAN + cols["keypoint_id"].astype(np.int64)
    xyz = np.stack([cols["x_pos"], cols["y_pos"], cols["z_pos"]], axis=1)
    key = frame * (_ID_SPAN * 64) + corner
    keys, inverse, count = np.unique(key, return_inverse=True, return_counts=True)
    mean = np.stack([np.bincount(inverse, weights=xyz[:, k]) / count for k in range(3)], 1)
    f, c = keys // (_ID_SPAN * 64), keys % (_ID_SPAN * 64)
    board = {int(k): tuple(v) for k, v in zip(session.corner, session.board_xy, strict=True)}
    keep = np.array([int(k) in board for k in c], dtype=bool)
    f, c, mean = f[keep], c[keep], mean[keep]
    if only is not None:
        pairs = _adjacent_pairs(f, c, board, session.square_m())
        d = np.array([np.linalg.norm(mean[i] - mean[j]) - session.square_m()
                      for i, j in pairs if (int(f[i]), int(c[i]), int(c[j])) in only])
    else:
        d = _spacing(f, c, mean, board, session.square_m())
    if not len(d):
        return 0, float("nan"), float("nan")
    return len(d), float(np.sqrt(np.mean(d**2)) * 1e3), float(np.mean(d) * 1e3)


def _adjacent_pairs(frame: np.ndarray, corner: np.ndarray, board: dict[int, tuple],
                    square_m: float) -> list[tuple[int, int]]:
    """Index pairs (i, j), corner[i] < corner[j], of board-adjacent corners in one frame."""
    out = []
    for i in range(len(frame)):  # scoring a few hundred points, not a hot path
        same = np.flatnonzero((frame == frame[i]) & (corner > corner[i])
                              & (corner // _ID_SPAN == corner[i] // _ID_SPAN))
        for j in same:
            d = np.hypot(*np.subtract(board[int(corner[i])], board[int(corner[j])]))
            if abs(d - square_m) < 1e-3 * square_m:
                out.append((i, int(j)))
    return out


def spacing_pairs(session: Session, frame: np.ndarray, rows: np.ndarray) -> set:
    """The (frame, corner, corner) adjacent pairs that `score_board` measured."""
    used = rows >= 0
    ids = np.where(used, session.corner[np.maximum(rows, 0)], -1)
    lo = np.where(used, ids, np.iinfo(np.int64).max).min(axis=1)
    hi = ids.max(axis=1)
    good = used.any(axis=1) & (lo == hi)
    board = {int(k): tuple(v) for k, v in zip(session.corner, session.board_xy, strict=True)}
    f, c = np.asarray(frame)[good], hi[good]
    return {(int(f[i]), int(c[i]), int(c[j]))
            for i, j in _adjacent_pairs(f, c, board, session.square_m())}


@dataclass(frozen=True)
class LostCorner:
    """Why a corner seen by >= 3 cameras came out as no point, measured with its id."""

    frame: int
    corner: int
    cameras: tuple[str, ...]
    worst_reproj_px: float  # its worst blob against the point its own blobs triangulate to
    worst_epipolar_px: float  # its worst camera pair's epipolar distance (larger way)
    time_spread_ms: float  # between its cameras' frame times
    cause: str


def classify_lost(session: Session, lost, epipolar_px: float, max_reproj_px: float
                  ) -> list[LostCorner]:
    """Each lost corner triangulated from all its blobs (the ids tell which): which gate
    its own blobs fail. Causes: 'reprojection gate' (a blob misses the point by more than
    max_reproj_px), 'epipolar gate' (a pair lies farther apart than epipolar_px), both, or
    'matching' (its blobs pass both gates: lost to a neighbour's conflict)."""
    obs, rig = session.obs, session.rig
    arrays = RigArrays.from_rig(rig)
    out = []
    for frame, corner in lost:
        rows = np.flatnonzero((obs.frame == frame) & (session.corner == corner))
        cam = obs.camera[rows].astype(np.int64)
        tri = triangulate(rig, np.zeros(len(rows), dtype=np.int64), cam, obs.uv[rows],
                          iterations=3, n_points=1)
        proj, _ = arrays.project(cam, np.repeat(tri.xyz, len(rows), axis=0))
        reproj = float(np.linalg.norm(proj - obs.uv[rows], axis=1).max())
        epi = _worst_epipolar(rig, cam, obs.uv[rows])
        spread = float(np.ptp(obs.t_ns[rows]) / 1e6)
        causes = [name for name, bad in (("reprojection gate", reproj > max_reproj_px),
                                         ("epipolar gate", epi > epipolar_px)) if bad]
        out.append(LostCorner(int(frame), int(corner), tuple(rig.names[c] for c in cam),
                              reproj, epi, spread, " + ".join(causes) or "matching"))
    return out


def _worst_epipolar(rig: Rig, cam: np.ndarray, uv: np.ndarray) -> float:
    """The largest epipolar distance (px, the larger of both ways) over camera pairs."""
    worst = 0.0
    for a in range(len(cam)):
        for b in range(a + 1, len(cam)):
            ca, cb = rig[int(cam[a])], rig[int(cam[b])]
            worst = max(worst, _epi(ca, cb, uv[a], uv[b]), _epi(cb, ca, uv[b], uv[a]))
    return worst


def _epi(ca, cb, uv_a, uv_b) -> float:
    """Distance (px of camera b) of uv_b from the epipolar line of uv_a."""
    R = cb.R @ ca.R.T
    t = cb.t - R @ ca.t
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    na = np.r_[ca.undistort(uv_a[None])[0], 1.0]
    nb = np.r_[cb.undistort(uv_b[None])[0], 1.0]
    line = tx @ R @ na
    return float(abs(line @ nb) * cb.fx / np.hypot(line[0], line[1]))
