"""Motive's table CSV (Format Version 1.2, 1.21, 1.22, 1.23, 1.24, ...): read into a MotiveTake.

The layout, as NaturalPoint's "Data Export: CSV" page describes it: line 1 holds the take's
properties as name,value pairs (Format Version, Take Name, Capture/Export Frame Rate,
Rotation Type, Length Units, Coordinate Space, ...); after a blank line come header rows
Type, Name, ID (Motive 2+ writes those words in column 2, 1.2x leaves it empty; a Parent
row may follow), a property row (Rotation, Position, Mean Marker Error, Marker Quality)
and the axis row `Frame,Time (Seconds),X,Y,Z,W,...`; then one row per frame, an empty cell
where nothing was seen. Columns are found by their headers, never by position, so any
selection of export options reads. Rotation Type is Quaternion or one of the six Euler
orders Motive offers (XYZ, XZY, YXZ, YZX, ZXY, ZYX), angles in degrees; Length Units
Meters, Centimeters or Millimeters. The header does not record the up axis: Motive's world
is y-up unless the export's axis convention changed it, so the caller says (default y);
our own files carry an `Up Axis` pair and are read by it.
"""

from __future__ import annotations

import csv
import io
import re
from pathlib import Path

import numpy as np

from calibkit.core.errors import UserError
from daemon.formats.motive_take import UNITS_M, MotiveBody, MotivePoses, MotiveTake
from daemon.tracking.rigid import matrix_from_quaternion, quaternion_xyzw

EULER_ORDERS = ("XYZ", "XZY", "YXZ", "YZX", "ZXY", "ZYX")


def _properties(row: list[str]) -> dict[str, str]:
    return {row[i].strip(): row[i + 1].strip() for i in range(0, len(row) - 1, 2)}


def _first_bad_line(path: Path, lines: list[str], numbers: list[int],
                    width: int) -> UserError:
    """The one-line error for the first data row that is not numbers (the error path only:
    a loop over the rows is fine here)."""
    for number, line in zip(numbers, lines, strict=True):
        cells = line.rstrip("\r\n").split(",")
        if len(cells) > width:
            return UserError(f"{path}:{number}: {len(cells)} cells, but the header names "
                             f"{width} columns")
        for c, cell in enumerate(cells):
            try:
                float(cell) if cell.strip() else None
            except ValueError:
                return UserError(f"{path}:{number}: {cell.strip()!r} in column {c + 1} is "
                                 "not a number")
    return UserError(f"{path}: the frame rows are not numbers")


def _numbers(path: Path, lines: list[str], numbers: list[int], width: int) -> np.ndarray:
    """The data rows as floats (F, width), empty cells NaN, in one parse; short rows (Motive
    leaves trailing empty cells out) padded with NaN."""
    block = "\n".join(ln.rstrip("\r\n") for ln in lines)
    block = re.sub(r"(?<=,)(?=,|$)", "nan", block, flags=re.M)
    block = re.sub(r"^,", "nan,", block, flags=re.M)
    counts = np.array([ln.count(",") + 1 for ln in block.split("\n")]) if block else []
    if len(counts) and (counts < width).any():
        pad = width - counts
        block = "\n".join(ln + ",nan" * int(p) for ln, p in zip(block.split("\n"), pad,
                                                               strict=True))
    try:
        data = np.loadtxt(io.StringIO(block), delimiter=",", ndmin=2, dtype=np.float64)
    except ValueError:
        raise _first_bad_line(path, lines, numbers, width) from None
    return data


def euler_matrix(deg: np.ndarray, order: str) -> np.ndarray:
    """Angles (F, 3) about X, Y, Z in degrees -> rotations, applied in `order` about the
    body's own (moving) axes, Motive's relative Euler convention (the NatNet samples' 'r'
    orders): 'XYZ' is R = Rx Ry Rz, 'ZYX' is R = Rz Ry Rx."""
    rad = np.radians(deg)
    out = np.tile(np.eye(3), (len(deg), 1, 1))
    for axis in order:
        a = rad[:, "XYZ".index(axis)]
        c, s = np.cos(a), np.sin(a)
        R = np.tile(np.eye(3), (len(deg), 1, 1))
        i, j = [(1, 2), (2, 0), (0, 1)]["XYZ".index(axis)]
        R[:, i, i], R[:, i, j], R[:, j, i], R[:, j, j] = c, -s, s, c
        out = np.matmul(out, R)
    return out


def _header(path: Path, lines: list[str]):
    """(header rows above the axis row, axis row, line number of the first data row)."""
    head = []
    for number, line in enumerate(lines[1:], 2):
        if not line.strip().strip(","):
            continue
        row = next(csv.reader([line]))
        head.append(row)
        if row[0].strip().lower() == "frame":
            return head[:-1], row, number
    raise UserError(f"{path}: no 'Frame,Time,...' header row; is this a Motive CSV with "
                    "its header exported?")


def read_table(path: Path, text: str, up_axis: str | None = None) -> MotiveTake:
    """A Format Version 1.2x export (see the module docstring); `up_axis` 'y' or 'z' when
    the caller knows the export's axis convention, else the file's Up Axis or y."""
    lines = text.splitlines()
    props = _properties(next(csv.reader([lines[0]])))
    units = props.get("Length Units", "Meters").strip().lower()
    if units not in UNITS_M:
        raise UserError(f"{path}:1: Length Units {units!r} is not Meters, Centimeters or "
                        "Millimeters")
    scale = UNITS_M[units]
    rotation = props.get("Rotation Type", "Quaternion").strip().upper()
    if rotation != "QUATERNION" and rotation not in EULER_ORDERS:
        raise UserError(f"{path}:1: Rotation Type {rotation!r} is neither Quaternion nor an "
                        f"Euler order ({', '.join(EULER_ORDERS)})")
    if props.get("Coordinate Space", "Global").lower() != "global":
        raise UserError(f"{path}:1: exported in {props['Coordinate Space']} coordinates; "
                        "export with Coordinate Space Global")
    up = (up_axis or props.get("Up Axis", "y")).strip().lower()
    if up not in ("y", "z"):
        raise UserError(f"{path}:1: Up Axis {up!r} is neither Y nor Z")
    rows, axes, data_from = _header(path, lines)
    if len(rows) < 4:
        raise UserError(f"{path}:{data_from - 1}: {len(rows)} header rows above "
                        "'Frame,Time'; Motive writes Type, Name, ID and the property row")
    width = len(axes)
    rows = [r + [""] * (width - len(r)) for r in rows]
    named = {r[1].strip().lower(): r for r in rows if r[1].strip()}
    typ = named.get("type", rows[0])
    name = named.get("name", rows[1])
    ident = named.get("id", rows[2])
    prop = rows[-1]
    numbers = [n for n, ln in enumerate(lines[data_from:], data_from + 1) if ln.strip()]
    if not numbers:
        raise UserError(f"{path}: the header is there but no frame follows")
    data = _numbers(path, [lines[n - 1] for n in numbers], numbers, width)
    if not np.isfinite(data[:, :2]).all():
        bad = int(np.flatnonzero(~np.isfinite(data[:, :2]).all(axis=1))[0])
        raise UserError(f"{path}:{numbers[bad]}: no frame number or time")
    frame = data[:, 0].astype(np.int64)
    t_s = data[:, 1]
    groups: dict[tuple[str, str], dict[str, dict[str, int]]] = {}
    ids: dict[tuple[str, str], str] = {}
    for c in range(2, width):
        key = (typ[c].strip(), name[c].strip())
        groups.setdefault(key, {}).setdefault(prop[c].strip(), {})[axes[c].strip().upper()] = c
        ids.setdefault(key, ident[c].strip())

    def xyz(where: str, cols: dict[str, int]) -> np.ndarray:
        missing = [a for a in "XYZ" if a not in cols]
        if missing:
            raise UserError(f"{path}:{data_from}: {where!r} has no {'/'.join(missing)} "
                            "column under its Position")
        return data[:, [cols["X"], cols["Y"], cols["Z"]]] * scale

    labels, labelled, unlabelled = [], [], []
    body_names = [n for (t, n) in groups if t == "Rigid Body"]
    poses: dict[str, MotivePoses] = {}
    for (kind, nm), props_ in groups.items():
        if kind == "Marker" and "Position" in props_:
            is_free = nm.lower().startswith("unlabeled")
            (unlabelled if is_free else labelled).append(xyz(nm, props_["Position"]))
            if not is_free:
                labels.append(nm)
        elif kind == "Rigid Body" and "Position" in props_ and "Rotation" in props_:
            poses[nm] = _poses(path, data_from, nm, data, xyz(nm, props_["Position"]),
                               props_, rotation, scale)
    bodies = []
    for number, nm in enumerate(body_names, 1):
        members = [(n, c["Position"]) for (t, n), c in groups.items()
                   if t == "Rigid Body Marker" and "Position" in c and _owner(n, body_names) == nm]
        offsets = _offsets_from_markers(poses.get(nm), [xyz(n, c) for n, c in members])
        raw = ids.get(("Rigid Body", nm), "")
        body_id = int(raw) if raw.isdigit() else number
        bodies.append(MotiveBody(nm, body_id, offsets, [n for n, _ in members]))
    n = len(data)
    return MotiveTake(frame, t_s, _rate(props, t_s), labels, _stack(labelled, n),
                      _stack(unlabelled, n), bodies, poses,
                      {"format": "modern", "format_version": props.get("Format Version", ""),
                       "take": props.get("Take Name", ""), "rotation": rotation,
                       "units": units, "up_axis": up})


def _poses(path, data_from, nm, data, p, props_, rotation, scale) -> MotivePoses:
    """One Rigid Body's pose columns: quaternion (X Y Z W) or Euler angles (X Y Z)."""
    rot = props_["Rotation"]
    want = "XYZW" if rotation == "QUATERNION" else "XYZ"
    missing = [a for a in want if a not in rot]
    if missing:
        raise UserError(f"{path}:{data_from}: rigid body {nm!r} has no Rotation "
                        f"{'/'.join(missing)} column (Rotation Type {rotation})")
    if rotation == "QUATERNION":
        q = data[:, [rot["X"], rot["Y"], rot["Z"], rot["W"]]]
    else:
        q = np.full((len(data), 4), np.nan)
        angles = data[:, [rot["X"], rot["Y"], rot["Z"]]]
        ok = np.isfinite(angles).all(axis=1)
        q[ok] = quaternion_xyzw(euler_matrix(angles[ok], rotation))
    err_col = next((props_[k][""] for k in ("Mean Marker Error", "Error Per Marker")
                    if k in props_ and "" in props_[k]), None)
    err = data[:, err_col] * scale if err_col is not None else np.full(len(data), np.nan)
    norm = np.linalg.norm(q, axis=1)
    valid = np.isfinite(p).all(axis=1) & np.isfinite(q).all(axis=1) & (norm > 0.5)
    safe = np.where(valid, norm, 1.0)[:, None]
    return MotivePoses(valid, np.where(valid[:, None], p, np.nan),
                       np.where(valid[:, None], q / safe, np.nan), err)


def _owner(marker_name: str, body_names: list[str]) -> str | None:
    """The body a 'Rigid Body Marker' column belongs to: the longest body name that
    starts its name before a ':' or '_' (Motive writes 'Body:Marker1' or 'Body_1')."""
    hits = [b for b in body_names if marker_name.startswith(b)
            and marker_name[len(b):len(b) + 1] in (":", "_")]
    return max(hits, key=len) if hits else None


def _offsets_from_markers(poses: MotivePoses | None, world: list[np.ndarray]) -> np.ndarray:
    """Template markers in the body frame from Motive's solved marker positions (world)
    and its poses: the median over the frames with both (they are the template moved by
    the pose, so every frame gives the same offsets up to rounding)."""
    if poses is None or not world:
        return np.zeros((0, 3))
    R = matrix_from_quaternion(np.nan_to_num(poses.quat_xyzw, nan=0.0) +
                               np.array([0, 0, 0, 1.0]) * ~poses.valid[:, None])
    out = []
    for w in world:
        ok = poses.valid & np.isfinite(w).all(axis=1)
        if not ok.any():
            return np.zeros((0, 3))
        local = np.einsum("fji,fj->fi", R[ok], w[ok] - poses.xyz_m[ok])
        out.append(np.median(local, axis=0))
    return np.array(out).reshape(-1, 3)


def _stack(columns: list[np.ndarray], n: int) -> np.ndarray:
    return np.stack(columns, axis=1) if columns else np.zeros((n, 0, 3))


def _rate(props: dict[str, str], t_s: np.ndarray) -> float:
    for key in ("Export Frame Rate", "Capture Frame Rate"):
        try:
            return float(props[key])
        except (KeyError, ValueError):
            continue
    dt = np.diff(t_s)
    return float(1.0 / np.median(dt)) if len(dt) and np.median(dt) > 0 else 0.0
