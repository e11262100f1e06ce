"""Motive's (and Arena's) row-typed CSV, formats 1.0 and 1.1: read into a MotiveTake.

The layout, as the files' own `comment` rows describe it: the first cell of every row
names its type. `comment` rows, `righthanded` (or `lefthanded`, refused), `info` rows
(`version` in 1.1, `framecount`, `trackablecount`/`rigidbodycount`), then the body
definitions: `trackable` (1.0) or `rigidbody` (1.1) rows `NAME,ID,K,x,y,z per marker`
(template markers in the body frame, metres). Then per frame a `frame` row
`INDEX,TIME,NBODIES, (ID,x,y,z,qx,qy,qz,qw,yaw,pitch,roll) per tracked body, NMARKERS,
marker detail` where a marker is `x,y,z,id` in 1.0 and `x,y,z,id,name` in 1.1, followed by
one extended `trackable`/`rigidbody` row per body (its fitted template, matched point-cloud
markers, tracked flags, quality and mean error: not needed here, skipped). A definition row
comes before the first frame; the same row type after it is the extended row.

Each frame row says how many markers it carries, so the marker detail's width (4 or 5) is
read off the row itself, not assumed from the version. Lengths are metres; the world is
Motive's (and Arena's) y-up. A 1.1 marker named `BODY-Marker N` is labelled `BODY:MarkerN`;
every other marker, and every 1.0 marker (they carry no name), is unlabelled.
"""

from __future__ import annotations

import csv
import io
from pathlib import Path

import numpy as np

from calibkit.core.errors import UserError
from daemon.formats.motive_take import MotiveBody, MotivePoses, MotiveTake

ROW_TYPES = {"comment", "info", "righthanded", "lefthanded", "rigidbody", "frame",
             "trackable"}
POSE_WIDTH = 11  # id, x y z, qx qy qz qw, yaw pitch roll


def _definition(path: Path, number: int, row: list[str]) -> MotiveBody:
    try:
        k = int(row[3])
        values = [float(v) for v in row[4:4 + 3 * k]]
        if k < 0 or len(values) != 3 * k:
            raise ValueError
        xyz = np.array(values).reshape(k, 3)
        body_id = int(row[2])
    except (ValueError, IndexError):
        raise UserError(f"{path}:{number}: a {row[0].strip()} definition row should be "
                        "name, id, marker count, x y z per marker") from None
    name = row[1].strip()
    return MotiveBody(name, body_id, xyz, [f"{name}:Marker{i + 1}" for i in range(k)])


def _frame_row(row: list[str]):
    """(index, time, [(id, 7 pose values)], [(x, y, z, name or None)]) from a frame row;
    ValueError/IndexError when it does not follow the layout."""
    while row and not row[-1].strip():
        row = row[:-1]
    index, t = int(row[1]), float(row[2])
    nb = int(row[3])
    if nb < 0:
        raise ValueError
    at = 4
    bodies = []
    for _ in range(nb):
        bodies.append((int(row[at]), [float(v) for v in row[at + 1:at + 8]]))
        if len(bodies[-1][1]) != 7:
            raise IndexError
        at += POSE_WIDTH
    nm = int(row[at])
    at += 1
    rest = len(row) - at
    if nm < 0 or (nm == 0 and rest) or (nm and (rest % nm or rest // nm not in (4, 5))):
        raise ValueError
    width = rest // nm if nm else 4
    cells = np.array(row[at:], dtype=object).reshape(nm, width)
    xyz = cells[:, :3].astype(np.float64)
    names = cells[:, 4].tolist() if width == 5 else [None] * nm
    return index, t, bodies, xyz, names


def read_rows(path: Path, text: str) -> MotiveTake:
    """A format 1.0 or 1.1 export (see the module docstring)."""
    definitions: list[MotiveBody] = []
    info: dict[str, str] = {}
    frames: list[tuple[int, list[str]]] = []
    definition_kind = None
    for number, row in enumerate(csv.reader(io.StringIO(text)), 1):
        if not row or not "".join(row).strip():
            continue
        kind = row[0].strip().lower()
        if kind == "lefthanded":
            raise UserError(f"{path}:{number}: a left-handed export; export it right-handed")
        if kind == "info" and len(row) >= 3:
            info[row[1].strip().lower()] = row[2].strip()
        elif kind in ("rigidbody", "trackable") and not frames:
            definitions.append(_definition(path, number, row))
            definition_kind = kind
        elif kind == "frame":
            frames.append((number, row))
        elif kind not in ROW_TYPES:
            raise UserError(f"{path}:{number}: unknown row type {row[0]!r} (Motive's row "
                            f"types are {', '.join(sorted(ROW_TYPES))})")
    if not frames:
        raise UserError(f"{path}: no 'frame' rows; nothing was exported")
    names = [b.name for b in definitions]
    if len(set(names)) != len(names):
        raise UserError(f"{path}: two rigid body definitions share a name")
    by_id = {b.id: b.name for b in definitions}
    n = len(frames)
    frame = np.zeros(n, dtype=np.int64)
    t_s = np.zeros(n)
    poses = {b.name: MotivePoses(np.zeros(n, bool), np.full((n, 3), np.nan),
                                 np.full((n, 4), np.nan), np.full(n, np.nan))
             for b in definitions}
    label_index: dict[str, int] = {}
    labelled_rows: list[tuple[int, int, np.ndarray]] = []
    free_frame: list[np.ndarray] = []
    free_xyz: list[np.ndarray] = []
    has_names = False
    for i, (number, row) in enumerate(frames):
        try:
            frame[i], t_s[i], bodies, xyz, marker_names = _frame_row(row)
        except (ValueError, IndexError):
            raise UserError(f"{path}:{number}: a frame row should be index, time, body "
                            "count, 11 values per body, marker count, then x y z id (1.0) "
                            "or x y z id name (1.1) per marker") from None
        for body_id, vals in bodies:
            name = by_id.get(body_id)
            q = np.array(vals[3:])
            if name is not None and np.isfinite(vals).all() and np.linalg.norm(q) > 0.5:
                pz = poses[name]
                pz.valid[i] = True
                pz.xyz_m[i] = vals[:3]
                pz.quat_xyzw[i] = q / np.linalg.norm(q)
        has_names |= bool(marker_names) and marker_names[0] is not None
        free = np.ones(len(xyz), bool)
        for m, nm in enumerate(marker_names):
            label = _row_label(nm, definitions) if nm is not None else None
            if label is not None:
                labelled_rows.append((i, label_index.setdefault(label, len(label_index)),
                                      xyz[m]))
                free[m] = False
        free_frame.append(np.full(int(free.sum()), i))
        free_xyz.append(xyz[free])
    labelled = np.full((n, len(label_index), 3), np.nan)
    for i, k, xyz in labelled_rows:
        labelled[i, k] = xyz
    unlabelled = _pack(np.concatenate(free_frame), np.concatenate(free_xyz).reshape(-1, 3), n)
    dt = np.diff(t_s)
    rate = float(1.0 / np.median(dt)) if len(dt) and np.median(dt) > 0 else 0.0
    version = info.get("version") or ("1.1" if definition_kind == "rigidbody" or has_names
                                      else "1.0")
    return MotiveTake(frame, t_s, rate, list(label_index), labelled, unlabelled, definitions,
                      poses, {"format": "rows", "format_version": version,
                              "rotation": "QUATERNION", "units": "meters", "up_axis": "y"})


def _pack(rows: np.ndarray, xyz: np.ndarray, n: int) -> np.ndarray:
    """Points (M, 3) with their frame (M,) as (n, widest frame, 3), NaN-padded."""
    counts = np.bincount(rows, minlength=n) if len(rows) else np.zeros(n, np.int64)
    out = np.full((n, int(counts.max(initial=0)), 3), np.nan)
    if len(rows):
        order = np.argsort(rows, kind="stable")
        start = np.concatenate([[0], np.cumsum(counts)[:-1]])
        slot = np.arange(len(rows)) - start[rows[order]]
        out[rows[order], slot] = xyz[order]
    return out


def _row_label(name: str, bodies: list[MotiveBody]) -> str | None:
    """'Rigid Body 1-Marker 3' -> 'Rigid Body 1:Marker3'; None for an unlabelled marker."""
    for b in bodies:
        if name.startswith(b.name + "-"):
            return f"{b.name}:{name[len(b.name) + 1:].replace(' ', '')}"
    return None
