"""OptiTrack Motive CSV exports: reading both layouts, writing the modern one.

Motive writes two kinds of CSV. The modern one (Format Version 1.2x) is a table: a line
of take properties, then header rows naming each column's Type (Rigid Body, Rigid Body
Marker, Marker), Name, ID and Property (Rotation, Position, Mean Marker Error, ...), and
a `Frame,Time,X,Y,Z,...` row; empty cells where nothing was seen. The old one (format
1.1) is row-typed: `info` rows, `rigidbody` definition rows with the body's template
markers, then per frame a `frame` row (every body's pose and every reconstructed marker)
and per body a `rigidbody` row. Both become one MotiveTake in metres and seconds: the
measured markers (labelled ones by name, unlabelled ones as a cloud), the rigid-body
definitions (template markers in the body frame, relative to the body's pivot, the
point Motive reports as its position) and Motive's own poses, the reference our tracking
is compared with. Quaternions are x y z w, body to world.
"""

from __future__ import annotations

import csv
import io
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from calibkit.core.errors import UserError
from calibkit.core.fileio import atomic_write
from daemon.rigid import matrix_from_quaternion, quaternion_xyzw

UNITS_M = {"meters": 1.0, "millimeters": 1e-3, "centimeters": 1e-2, "m": 1.0, "mm": 1e-3,
           "cm": 1e-2}
ROW_TYPES = {"comment", "info", "righthanded", "lefthanded", "rigidbody", "frame",
             "trackable"}


@dataclass(eq=False)
class MotiveBody:
    """A rigid body as Motive defines it: template markers (K, 3) metres in the body frame,
    relative to the pivot Motive reports as the body's position."""

    name: str
    id: int
    offsets_m: np.ndarray
    marker_names: list[str] = field(default_factory=list)


@dataclass(eq=False)
class MotivePoses:
    """One body's poses as Motive solved them, a row per frame of the take."""

    valid: np.ndarray  # (F,) bool
    xyz_m: np.ndarray  # (F, 3), NaN when not tracked
    quat_xyzw: np.ndarray  # (F, 4)
    error_m: np.ndarray  # (F,) Motive's mean marker error, NaN when not given


@dataclass(eq=False)
class MotiveTake:
    frame: np.ndarray  # (F,)
    t_s: np.ndarray  # (F,)
    rate_hz: float
    labels: list[str]
    labelled_m: np.ndarray  # (F, K, 3) NaN where not seen
    unlabelled_m: np.ndarray  # (F, U, 3) NaN-padded
    bodies: list[MotiveBody]
    poses: dict[str, MotivePoses]
    meta: dict = field(default_factory=dict)

    def all_markers(self) -> np.ndarray:
        """Every measured marker, labelled or not, as one (F, K + U, 3) cloud."""
        return np.concatenate([self.labelled_m, self.unlabelled_m], axis=1)


def sniff(path: Path) -> str | None:
    """'modern' or 'rows' for a Motive CSV, None for anything else (by its first cell)."""
    try:
        with open(path, encoding="utf-8-sig", errors="replace") as handle:
            first = handle.readline()
    except OSError:
        return None
    cells = [c.strip().strip('"').lower() for c in first.split(",", 2)]
    if cells[0] == "format version":
        return "modern"
    if cells[0] == "frame":  # a row-typed frame row, or a header such as ours (frame,x,...)
        return "rows" if len(cells) > 1 and cells[1].isdigit() else None
    if cells[0] in ROW_TYPES:
        return "rows"
    return None


def read_motive_csv(path: str | Path) -> MotiveTake:
    """A Motive CSV export of either layout (see the module docstring)."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"{path} not found")
    kind = sniff(path)
    if kind is None:
        raise UserError(f"{path} is not a Motive CSV export (it starts neither with "
                        "'Format Version' nor with Motive's row types)")
    try:
        text = path.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError:
        raise UserError(f"{path} is not a text CSV file") from None
    return _read_modern(path, text) if kind == "modern" else _read_rows(path, text)


# ---- the modern layout -------------------------------------------------------------------

def _properties(row: list[str]) -> dict[str, str]:
    return {row[i].strip(): row[i + 1].strip() for i in range(0, len(row) - 1, 2)}


def _numbers(path: Path, lines: list[str], first_line: int, width: int) -> np.ndarray:
    """The data rows as floats (F, width), empty cells NaN, in one parse."""
    block = "\n".join(ln.rstrip("\r\n") for ln in lines)
    block = re.sub(r"(?<=,)(?=,|$)", "nan", block, flags=re.M)
    block = re.sub(r"^,", "nan,", block, flags=re.M)
    try:
        data = np.loadtxt(io.StringIO(block), delimiter=",", ndmin=2, dtype=np.float64)
    except ValueError as exc:
        where = re.search(r"line (\d+)", str(exc))
        line = f" line {first_line + int(where.group(1)) - 1}" if where else ""
        raise UserError(f"{path}:{line} not a number where one is expected "
                        f"({str(exc).splitlines()[0]})") from None
    if data.shape[1] < width:
        data = np.hstack([data, np.full((len(data), width - data.shape[1]), np.nan)])
    return data


def _euler_matrix(deg: np.ndarray, order: str) -> np.ndarray:
    """Angles (F, 3) about X, Y, Z in degrees -> rotations, applied in `order` about the
    body's own (moving) axes, Motive's relative Euler convention: 'XYZ' is R = Rx Ry Rz."""
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


def _read_modern(path: Path, text: str) -> MotiveTake:
    lines = text.splitlines()
    props = _properties(next(csv.reader([lines[0]])))
    units = props.get("Length Units", "Meters").lower()
    if units not in UNITS_M:
        raise UserError(f"{path}: Length Units {units!r} is not meters, centimeters or "
                        "millimeters")
    scale = UNITS_M[units]
    rotation = props.get("Rotation Type", "Quaternion").strip().upper()
    if rotation != "QUATERNION" and sorted(rotation) != ["X", "Y", "Z"]:
        raise UserError(f"{path}: Rotation Type {rotation!r} is neither Quaternion nor an "
                        "Euler order such as XYZ")
    if props.get("Coordinate Space", "Global").lower() != "global":
        raise UserError(f"{path}: exported in {props['Coordinate Space']} coordinates; "
                        "export with Coordinate Space Global")
    head = []
    for number, line in enumerate(lines[1:], 2):
        if not line.strip().strip(","):
            continue
        row = next(csv.reader([line]))
        head.append(row)
        if row[0].strip().lower() == "frame":
            data_from = number
            break
    else:
        raise UserError(f"{path}: no 'Frame,Time,...' header row; is this a Motive CSV with "
                        "its header exported?")
    axes, rows = head[-1], head[:-1]
    if len(rows) < 4:
        raise UserError(f"{path}: {len(rows)} header rows above 'Frame,Time'; Motive writes "
                        "Type, Name, ID and the property row")
    width = len(axes)
    rows = [r + [""] * (width - len(r)) for r in rows]
    named = {r[1].strip().lower(): r for r in rows if r[1].strip()}
    typ = named.get("type", rows[0])
    name = named.get("name", rows[1])
    ident = named.get("id", rows[2])
    prop = rows[-1]
    data = _numbers(path, [ln for ln in lines[data_from:] if ln.strip()], data_from + 1,
                    width)
    if not len(data):
        raise UserError(f"{path}: the header is there but no frame follows")
    frame = data[:, 0].astype(np.int64)
    t_s = data[:, 1]
    groups: dict[tuple[str, str], dict[str, dict[str, int]]] = {}
    ids: dict[tuple[str, str], str] = {}
    for c in range(2, width):
        key = (typ[c].strip(), name[c].strip())
        groups.setdefault(key, {}).setdefault(prop[c].strip(), {})[axes[c].strip().upper()] = c
        ids.setdefault(key, ident[c].strip())

    def xyz(cols: dict[str, int]) -> np.ndarray:
        return data[:, [cols["X"], cols["Y"], cols["Z"]]] * scale

    labels, labelled, unlabelled = [], [], []
    body_names = [n for (t, n) in groups if t == "Rigid Body"]
    poses: dict[str, MotivePoses] = {}
    for (kind, nm), props_ in groups.items():
        if kind == "Marker" and "Position" in props_:
            (unlabelled if nm.lower().startswith("unlabeled") else labelled).append(
                xyz(props_["Position"]))
            if not nm.lower().startswith("unlabeled"):
                labels.append(nm)
        elif kind == "Rigid Body" and "Position" in props_ and "Rotation" in props_:
            p = xyz(props_["Position"])
            rot = props_["Rotation"]
            if rotation == "QUATERNION":
                q = data[:, [rot["X"], rot["Y"], rot["Z"], rot["W"]]]
            else:
                q = np.full((len(data), 4), np.nan)
                ok = np.isfinite(data[:, [rot["X"], rot["Y"], rot["Z"]]]).all(axis=1)
                q[ok] = quaternion_xyzw(_euler_matrix(
                    data[ok][:, [rot["X"], rot["Y"], rot["Z"]]], rotation))
            err_col = next((props_[k][""] for k in ("Mean Marker Error", "Error Per Marker")
                            if k in props_ and "" in props_[k]), None)
            err = data[:, err_col] * scale if err_col is not None else np.full(len(data), np.nan)
            valid = np.isfinite(p).all(axis=1) & np.isfinite(q).all(axis=1)
            norm = np.linalg.norm(np.where(valid[:, None], q, 1.0), axis=1)
            poses[nm] = MotivePoses(valid, np.where(valid[:, None], p, np.nan),
                                    np.where(valid[:, None], q / norm[:, None], np.nan), err)
    bodies = []
    for number, nm in enumerate(body_names, 1):
        members = [(n, c["Position"]) for (t, n), c in groups.items()
                   if t == "Rigid Body Marker" and "Position" in c and _owner(n, body_names) == nm]
        offsets = _offsets_from_markers(poses.get(nm), [xyz(c) for _, c in members])
        raw = ids.get(("Rigid Body", nm), "")
        body_id = int(raw) if raw.isdigit() else number
        bodies.append(MotiveBody(nm, body_id, offsets, [n for n, _ in members]))
    n = len(data)
    return MotiveTake(frame, t_s, _rate(props, t_s), labels, _stack(labelled, n),
                      _stack(unlabelled, n), bodies, poses,
                      {"format": "modern", "format_version": props.get("Format Version", ""),
                       "take": props.get("Take Name", ""), "rotation": rotation,
                       "units": units})


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


# ---- the old row-typed layout ------------------------------------------------------------

def _read_rows(path: Path, text: str) -> MotiveTake:
    definitions: list[MotiveBody] = []
    info: dict[str, str] = {}
    frames: list[list[str]] = []
    for number, row in enumerate(csv.reader(io.StringIO(text)), 1):
        if not row:
            continue
        kind = row[0].strip().lower()
        if kind == "lefthanded":
            raise UserError(f"{path}: a left-handed export; export it right-handed")
        if kind == "trackable":
            raise UserError(f"{path}:{number}: 'trackable' rows (Motive's format 1.0) are "
                            "not read; export the take again as CSV from Motive")
        if kind == "info" and len(row) >= 3:
            info[row[1].strip()] = row[2].strip()
        elif kind == "rigidbody" and not frames:
            try:
                k = int(row[3])
                xyz = np.array([float(v) for v in row[4:4 + 3 * k]]).reshape(k, 3)
                definitions.append(MotiveBody(row[1], int(row[2]), xyz,
                                              [f"{row[1]}:Marker{i + 1}" for i in range(k)]))
            except (ValueError, IndexError):
                raise UserError(f"{path}:{number}: a rigidbody definition row should be "
                                "name, id, marker count, x y z per marker") from None
        elif kind == "frame":
            frames.append((number, row))
        elif kind not in ROW_TYPES:
            raise UserError(f"{path}:{number}: unknown row type {row[0]!r}")
    if not frames:
        raise UserError(f"{path}: no 'frame' rows; nothing was exported")
    by_id = {b.id: b.name for b in definitions}
    n = len(frames)
    frame = np.zeros(n, dtype=np.int64)
    t_s = np.zeros(n)
    poses = {b.name: MotivePoses(np.zeros(n, bool), np.full((n, 3), np.nan),
                                 np.full((n, 4), np.nan), np.full(n, np.nan))
             for b in definitions}
    label_index: dict[str, int] = {}
    labelled_rows, unlabelled_rows = [], []
    for i, (number, row) in enumerate(frames):
        try:
            frame[i], t_s[i] = int(row[1]), float(row[2])
            nb = int(row[3])
            at = 4
            for _ in range(nb):
                body_id = int(row[at])
                vals = np.array([float(v) for v in row[at + 1:at + 8]])
                name = by_id.get(body_id)
                if name is not None and np.isfinite(vals).all():
                    pz = poses[name]
                    pz.valid[i] = True
                    pz.xyz_m[i] = vals[:3]
                    pz.quat_xyzw[i] = vals[3:] / np.linalg.norm(vals[3:])
                at += 11
            nm = int(row[at])
            at += 1
            for _ in range(nm):
                xyz = [float(v) for v in row[at:at + 3]]
                name = row[at + 4].strip()
                at += 5
                label = _row_label(name, definitions)
                if label is None:
                    unlabelled_rows.append((i, xyz))
                else:
                    k = label_index.setdefault(label, len(label_index))
                    labelled_rows.append((i, k, xyz))
        except (ValueError, IndexError):
            raise UserError(f"{path}:{number}: a frame row should be index, time, body "
                            "count, 11 values per body, marker count, x y z id name per "
                            "marker") from None
    labelled = np.full((n, len(label_index), 3), np.nan)
    for i, k, xyz in labelled_rows:
        labelled[i, k] = xyz
    counts = np.bincount([i for i, _ in unlabelled_rows], minlength=n)
    unlabelled = np.full((n, int(counts.max(initial=0)), 3), np.nan)
    slot = np.zeros(n, dtype=np.int64)
    for i, xyz in unlabelled_rows:
        unlabelled[i, slot[i]] = xyz
        slot[i] += 1
    dt = np.diff(t_s)
    rate = float(1.0 / np.median(dt)) if len(dt) and np.median(dt) > 0 else 0.0
    return MotiveTake(frame, t_s, rate, list(label_index), labelled, unlabelled, definitions,
                      poses, {"format": "rows", "format_version": info.get("version", ""),
                              "rotation": "QUATERNION", "units": "meters"})


def _row_label(name: str, bodies: list[MotiveBody]) -> str | None:
    """'Rigid Body 1-Marker 3' -> 'Rigid Body 1:Marker3'; None for an unlabelled marker."""
    for b in bodies:
        if name.startswith(b.name + "-"):
            return f"{b.name}:{name[len(b.name) + 1:].replace(' ', '')}"
    return None


# ---- writing -------------------------------------------------------------------------------

def write_motive_csv(path: str | Path, take: MotiveTake, take_name: str = "mocapd") -> None:
    """The take in Motive's modern layout (Format Version 1.23, metres, quaternions): each
    body's pose and mean marker error, its template markers where the pose puts them
    (Rigid Body Marker, from which a reader recovers the definition), the labelled markers
    and the unlabelled ones. Written whole or not at all."""
    n = len(take.frame)
    typ, name, ident, prop, axis, cols = [], [], [], [], [], []

    def add(kind, nm, idv, pr, axes, values):
        for a in range(len(axes)):
            typ.append(kind)
            name.append(nm)
            ident.append(str(idv))
            prop.append(pr)
            axis.append(axes[a])
            cols.append(values[:, a])

    for b in take.bodies:
        pz = take.poses.get(b.name)
        if pz is None:
            continue
        add("Rigid Body", b.name, b.id, "Rotation", "XYZW", pz.quat_xyzw)
        add("Rigid Body", b.name, b.id, "Position", "XYZ", pz.xyz_m)
        add("Rigid Body", b.name, b.id, "Mean Marker Error", [""], pz.error_m[:, None])
        R = matrix_from_quaternion(np.nan_to_num(pz.quat_xyzw, nan=0.0)
                                   + np.array([0, 0, 0, 1.0]) * ~pz.valid[:, None])
        for k, off in enumerate(b.offsets_m):
            world = np.einsum("fij,j->fi", R, off) + pz.xyz_m
            world[~pz.valid] = np.nan
            add("Rigid Body Marker", f"{b.name}:Marker{k + 1}", b.id, "Position", "XYZ",
                world)
    for k, label in enumerate(take.labels):
        add("Marker", label, k + 1, "Position", "XYZ", take.labelled_m[:, k])
    for u in range(take.unlabelled_m.shape[1]):
        add("Marker", f"Unlabeled:{u + 1}", f"U{u + 1}", "Position", "XYZ",
            take.unlabelled_m[:, u])
    props = ["Format Version", "1.23", "Take Name", take_name,
             "Capture Frame Rate", f"{take.rate_hz:.6f}", "Export Frame Rate",
             f"{take.rate_hz:.6f}", "Total Frames in Take", str(n), "Total Exported Frames",
             str(n), "Rotation Type", "Quaternion", "Length Units", "Meters",
             "Coordinate Space", "Global"]
    values = np.column_stack(cols) if cols else np.zeros((n, 0))
    with atomic_write(path, "w", newline="", encoding="utf-8") as handle:
        out = csv.writer(handle, lineterminator="\n")
        out.writerow(props)
        out.writerow([])
        out.writerow(["", "Type"] + typ)
        out.writerow(["", "Name"] + name)
        out.writerow(["", "ID"] + ident)
        out.writerow(["", ""] + prop)
        out.writerow(["Frame", "Time (Seconds)"] + axis)
        text = np.char.mod("%.6f", values)
        text[~np.isfinite(values)] = ""
        handle.writelines(f"{f},{t:.6f}," + ",".join(row) + "\n"
                          for f, t, row in zip(take.frame.tolist(), take.t_s.tolist(),
                                               text.tolist(), strict=True))
