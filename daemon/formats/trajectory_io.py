"""Reading and writing pose trajectories: TUM text files and CSV files with named columns.

A robot's own estimate usually comes as TUM (`t x y z qx qy qz qw`, what SLAM and VIO
evaluation tools exchange) or as a CSV log with a header; ours comes as a CSV of poses per
body. One reader takes both, so `mocapd evaluate` compares whatever a lab has.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from calibkit.core.errors import UserError
from calibkit.core.fileio import atomic_write, write_text_atomic

# accepted header names for each field, lower case; the first match wins
TIME_COLUMNS = ("t_s", "time_s", "timestamp", "time", "t", "t_ns", "time_ns", "timestamp_ns")
AXES = {"x": ("x", "tx", "pos_x", "x_m"), "y": ("y", "ty", "pos_y", "y_m"),
        "z": ("z", "tz", "pos_z", "z_m"), "qx": ("qx", "rot_x", "quat_x"),
        "qy": ("qy", "rot_y", "quat_y"), "qz": ("qz", "rot_z", "quat_z"),
        "qw": ("qw", "rot_w", "quat_w")}
BODY_COLUMNS = ("body", "name", "rigid_body")
UNITS = {"m": 1.0, "mm": 1e-3, "cm": 1e-2}


@dataclass(frozen=True, eq=False)
class Trajectory:
    """Poses in time: t_s (N,) increasing, xyz (N, 3) metres, quat (N, 4) x y z w unit."""

    t_s: np.ndarray
    xyz: np.ndarray
    quat: np.ndarray
    name: str = ""

    def __len__(self) -> int:
        return len(self.t_s)

    def select(self, keep: np.ndarray) -> Trajectory:
        return Trajectory(self.t_s[keep], self.xyz[keep], self.quat[keep], self.name)


def _finish(t_s, xyz, quat, name: str, where: str) -> Trajectory:
    t_s, xyz, quat = (np.asarray(a, dtype=np.float64) for a in (t_s, xyz, quat))
    keep = np.isfinite(t_s) & np.isfinite(xyz).all(axis=1) & np.isfinite(quat).all(axis=1)
    t_s, xyz, quat = t_s[keep], xyz[keep], quat[keep]
    norm = np.linalg.norm(quat, axis=1)
    if len(t_s) and np.any(np.abs(norm - 1.0) > 0.05):
        bad = int(np.argmax(np.abs(norm - 1.0) > 0.05))
        raise UserError(f"{where}: row {bad + 1} has a quaternion of length {norm[bad]:.3f}; "
                        "expected x y z w of a unit quaternion")
    order = np.argsort(t_s, kind="stable")
    t_s, xyz, quat = t_s[order], xyz[order], quat[order] / norm[order, None]
    if len(t_s) > 1 and np.any(np.diff(t_s) <= 0):
        raise UserError(f"{where}: two poses share a timestamp; one pose per time is needed")
    if len(t_s) < 10:
        raise UserError(f"{where}: {len(t_s)} valid poses; at least 10 are needed")
    return Trajectory(t_s, xyz, quat, name)


def read_tum(path: Path, scale: float = 1.0) -> Trajectory:
    """TUM format: one pose a line, `timestamp tx ty tz qx qy qz qw`, '#' comments."""
    rows = []
    with open(path, encoding="utf-8") as handle:
        for number, line in enumerate(handle, 1):
            text = line.split("#", 1)[0].replace(",", " ").split()
            if not text:
                continue
            if len(text) != 8:
                raise UserError(f"{path}:{number}: a TUM line has 8 numbers (t x y z qx qy "
                                f"qz qw), this one has {len(text)}")
            try:
                rows.append([float(v) for v in text])
            except ValueError:
                raise UserError(f"{path}:{number}: not a number in {line.strip()!r}") from None
    data = np.array(rows).reshape(-1, 8)
    return _finish(data[:, 0], data[:, 1:4] * scale, data[:, 4:8], path.stem, str(path))


def _column(header: list[str], names: tuple[str, ...]) -> int | None:
    lower = [h.strip().lower() for h in header]
    for n in names:
        if n in lower:
            return lower.index(n)
    return None


def read_csv(path: Path, body: str | None = None, scale: float = 1.0) -> Trajectory:
    """A CSV with a header naming time, x y z and qx qy qz qw columns (see TIME_COLUMNS and
    AXES); with a body column, `body` picks one body's rows."""
    with open(path, encoding="utf-8", newline="") as handle:
        reader = csv.reader(line for line in handle if not line.startswith("#"))
        header = next(reader, None)
        if header is None:
            raise UserError(f"{path}: the file is empty")
        rows = list(reader)
    t_col = _column(header, TIME_COLUMNS)
    cols = {k: _column(header, v) for k, v in AXES.items()}
    missing = [k for k, c in cols.items() if c is None]
    if t_col is None or missing:
        need = (["a time column (t_s, timestamp, ...)"] if t_col is None else []) + missing
        raise UserError(f"{path}: no column for {', '.join(need)}; the header is "
                        f"{','.join(header)}")
    b_col = _column(header, BODY_COLUMNS)
    if b_col is not None:
        names = sorted({r[b_col] for r in rows if len(r) > b_col})
        if body is None and len(names) > 1:
            raise UserError(f"{path} holds several bodies ({', '.join(names)}): choose one "
                            "with --body")
        if body is not None and body not in names:
            raise UserError(f"{path} has no body {body!r}; it has {', '.join(names)}")
        if body is not None:
            rows = [r for r in rows if len(r) > b_col and r[b_col] == body]
    elif body is not None:
        raise UserError(f"{path} has no body column, so --body {body} cannot pick one")
    used = [t_col, cols["x"], cols["y"], cols["z"], cols["qx"], cols["qy"], cols["qz"],
            cols["qw"]]
    need = max(used) + 1
    try:
        data = np.array([[float(r[i]) if r[i].strip() else np.nan for i in used]
                         for r in rows if len(r) >= need]).reshape(-1, len(used))
    except ValueError as exc:
        raise UserError(f"{path}: {exc}") from None
    t_col, cols = 0, dict(zip(("x", "y", "z", "qx", "qy", "qz", "qw"), range(1, 8), strict=True))
    t = data[:, t_col]
    if header[used[0]].strip().lower().endswith("_ns"):
        t = t * 1e-9
    xyz = data[:, [cols["x"], cols["y"], cols["z"]]] * scale
    quat = data[:, [cols["qx"], cols["qy"], cols["qz"], cols["qw"]]]
    return _finish(t, xyz, quat, body or path.stem, str(path))


def read_trajectory(path: str | Path, fmt: str = "auto", body: str | None = None,
                    units: str = "m") -> Trajectory:
    """A trajectory from a file; fmt 'tum', 'csv' or 'auto' (a header line means CSV)."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"{path} not found")
    if units not in UNITS:
        raise UserError(f"--units must be one of {', '.join(UNITS)}, got {units!r}")
    if fmt == "auto":
        with open(path, encoding="utf-8") as handle:
            first = next((ln for ln in handle if ln.strip() and not ln.startswith("#")), "")
        fmt = "csv" if any(c.isalpha() for c in first.replace("e-", "").replace("e+", "")) \
            else "tum"
    if fmt == "tum":
        return read_tum(path, UNITS[units])
    if fmt == "csv":
        return read_csv(path, body, UNITS[units])
    raise UserError(f"--format must be auto, tum or csv, got {fmt!r}")


def write_tum(path: str | Path, traj: Trajectory) -> None:
    """The trajectory as a TUM file (written whole or not at all)."""
    rows = np.column_stack([traj.t_s, traj.xyz, traj.quat])
    lines = ["# timestamp tx ty tz qx qy qz qw"]
    lines += [" ".join(f"{v:.9f}" for v in row) for row in rows]
    write_text_atomic(path, "\n".join(lines) + "\n")


# ---- the poses CSV of `mocapd track`: every body in every frame ------------------------------

ROWS_BLOCK_FRAMES = 4096  # frames of poses formatted at once when writing
POSES_COLUMNS = ("frame", "t_s", "body", "id", "valid", "x", "y", "z", "qx", "qy", "qz", "qw",
                 "error_mm", "markers")


@dataclass(frozen=True, eq=False)
class PoseTable:
    """Poses of several bodies per frame: (F,) frames and times, (F, B, ...) per body, NaN
    where a body has no valid pose."""

    frame: np.ndarray
    t_s: np.ndarray
    names: list[str]
    ids: np.ndarray
    valid: np.ndarray
    xyz: np.ndarray
    quat: np.ndarray
    error_mm: np.ndarray
    markers: np.ndarray

    def trajectory(self, name: str) -> Trajectory:
        b = self.names.index(name)
        v = self.valid[:, b]
        return Trajectory(self.t_s[v], self.xyz[v, b], self.quat[v, b], name)


def write_poses_csv(path: str | Path, table: PoseTable, comment: str = "") -> None:
    """One row per frame and body, frame-major; an invalid pose keeps its row (valid 0)
    with the pose fields empty. Metres, quaternions x y z w body-to-world, to 0.1 um and
    1e-8; written whole or not at all, a block of frames at a time (an hour-long take's
    rows never sit in memory as Python objects all at once)."""
    with atomic_write(path, "w", newline="", encoding="utf-8") as handle:
        if comment:
            handle.write(f"# {comment}\n")
        handle.write(",".join(POSES_COLUMNS) + "\n")
        write_poses_rows(handle, table)


def write_poses_rows(handle, table: PoseTable) -> None:
    """write_poses_csv's rows for the frames of `table`: a take written a window of
    frames at a time (mocapd track on a big points CSV) calls it once per window."""
    n_frames, n_bodies = table.valid.shape
    names = [n.replace(",", "_") for n in table.names]
    ids = table.ids.tolist()
    for a in range(0, n_frames, ROWS_BLOCK_FRAMES):
        b = min(a + ROWS_BLOCK_FRAMES, n_frames)
        frames, times = table.frame[a:b].tolist(), table.t_s[a:b].tolist()
        pose = np.concatenate([table.xyz[a:b], table.quat[a:b],
                               table.error_mm[a:b, :, None]], axis=2)
        rows = pose.reshape(-1, 8).tolist()
        valid = table.valid[a:b].reshape(-1).tolist()
        count = table.markers[a:b].reshape(-1).tolist()
        lines = []
        for i in range((b - a) * n_bodies):  # file output, a row at a time
            f, k = divmod(i, n_bodies)
            if valid[i]:
                x, y, z, qx, qy, qz, qw, e = rows[i]
                lines.append(f"{frames[f]},{times[f]:.6f},{names[k]},{ids[k]},1,{x:.7f},"
                             f"{y:.7f},{z:.7f},{qx:.8f},{qy:.8f},{qz:.8f},{qw:.8f},"
                             f"{e:.4f},{count[i]}\n")
            else:
                lines.append(f"{frames[f]},{times[f]:.6f},{names[k]},{ids[k]},0,,,,,,,,,"
                             f"{count[i]}\n")
        handle.writelines(lines)


def read_poses_csv(path: str | Path) -> PoseTable:
    """A poses CSV as `mocapd track` writes it (see write_poses_csv)."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"{path} not found")
    with open(path, encoding="utf-8", newline="") as handle:
        reader = csv.reader(line for line in handle if not line.startswith("#"))
        header = [h.strip().lower() for h in next(reader, [])]
        if tuple(header[:len(POSES_COLUMNS)]) != POSES_COLUMNS:
            raise UserError(f"{path}: not a poses CSV (its header should be "
                            f"{','.join(POSES_COLUMNS)})")
        rows = list(reader)
    names = list(dict.fromkeys(r[2] for r in rows))
    n_bodies = len(names)
    if not rows or len(rows) % n_bodies:
        raise UserError(f"{path}: {len(rows)} rows do not make whole frames of "
                        f"{n_bodies} bodies")
    try:
        num = np.array([[float(v) if v.strip() else np.nan for v in (r[:2] + r[3:])]
                        for r in rows]).reshape(-1, n_bodies, len(POSES_COLUMNS) - 1)
    except ValueError as exc:
        raise UserError(f"{path}: {exc}") from None
    return PoseTable(num[:, 0, 0].astype(np.int64), num[:, 0, 1], names,
                     num[0, :, 2].astype(np.int64), num[:, :, 3] > 0, num[:, :, 4:7],
                     num[:, :, 7:11], num[:, :, 11], num[:, :, 12].astype(np.int64))
