"""OptiTrack Motive CSV exports: every layout Motive writes read into one MotiveTake; 1.2x written.

Motive writes two kinds of CSV. The table (Format Version 1.2, 1.21, 1.22, 1.23, 1.24, ...)
is read by daemon.formats.motive_csv_table; the row-typed one (format 1.0 with `trackable`
rows, Arena's and early Motive's, and 1.1 with `rigidbody` rows) by
daemon.formats.motive_csv_rows. Both become one MotiveTake (daemon.formats.motive_take) in
metres and seconds, in the file's own world (Motive's is y-up; `meta['up_axis']` says) with
the measured markers, the rigid-body definitions (template markers in the body frame,
relative to the pivot Motive reports as the body's position) and Motive's own poses, the
reference our tracking is compared with. Quaternions are x y z w, body to world.
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from calibkit.core.errors import UserError
from calibkit.core.fileio import atomic_write
from daemon.formats.motive_csv_rows import ROW_TYPES, read_rows
from daemon.formats.motive_csv_table import read_table
from daemon.formats.motive_take import (  # noqa: F401  (the types, re-exported)
    UNITS_M,
    MotiveBody,
    MotivePoses,
    MotiveTake,
    to_z_up,
)
from daemon.tracking.rigid import matrix_from_quaternion


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


def read_motive_csv(path: str | Path, up_axis: str | None = None) -> MotiveTake:
    """A Motive CSV export of any layout, in the file's own world. `up_axis` ('y' or 'z')
    overrides what the file implies (Motive's default y-up) for a table export made with
    another axis convention; the row-typed formats are always y-up."""
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
    if kind == "modern":
        return read_table(path, text, up_axis)
    take = read_rows(path, text)
    if up_axis is not None:
        take.meta["up_axis"] = up_axis
    return take


# ---- writing -------------------------------------------------------------------------------

def write_motive_csv(path: str | Path, take: MotiveTake, take_name: str = "mocapd") -> None:
    """The take in Motive's table layout (Format Version 1.23, metres, quaternions) in the
    take's own world, its up axis recorded as an `Up Axis` pair on the property line (Motive
    writes none; readers of name,value pairs pass over it): each body's pose and mean
    marker error, its template markers where the pose puts them (Rigid Body Marker, from
    which a reader recovers the definition), the labelled markers and the unlabelled ones.
    Written whole or not at all."""
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
             "Coordinate Space", "Global", "Up Axis", take.up_axis.upper()]
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
