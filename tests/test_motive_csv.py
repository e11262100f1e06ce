"""Motive CSV: every layout read, from real exports (1.1, 1.21) and from small files written by
hand from the published layouts (1.0, 1.1, 1.2x with every Rotation Type, unit and up axis)
with known poses; the table layout written and read back; malformed files one clear line."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest

from calibkit.core.errors import UserError
from daemon.formats.motive_csv import read_motive_csv, write_motive_csv
from daemon.tracking.rigid import matrix_from_quaternion

DATA = Path(__file__).resolve().parent.parent / "fixtures" / "optitrack_rigidbody_csv"
MODERN = DATA / "sample_optitrack_take.csv"
ROWS = DATA / "v1.1.csv"


def test_modern_layout_markers_bodies_and_poses():
    take = read_motive_csv(MODERN)
    assert take.meta["format_version"] == "1.21" and take.rate_hz == 120.0
    assert len(take.frame) == 250 and take.frame[0] == 0
    assert take.t_s[1] == pytest.approx(1 / 120, abs=1e-6)
    assert take.labels == [f"Rigid Body 1:Marker{i}" for i in (1, 2, 3)]
    # six Unlabeled columns, three of them empty in every frame
    assert take.unlabelled_m.shape == (250, 6, 3)
    assert np.isfinite(take.unlabelled_m).all(axis=2).sum(axis=1).tolist() == [3] * 250
    assert take.unlabelled_m[0, 0] == pytest.approx([-0.724127, 0.716956, 2.824065])
    (body,) = take.bodies
    assert body.name == "Rigid Body 1" and len(body.offsets_m) == 3
    poses = take.poses["Rigid Body 1"]
    assert poses.valid.all()
    assert poses.xyz_m[0] == pytest.approx([0.060002, 0.019150, 0.076611])
    assert poses.error_m[0] == pytest.approx(4e-6)
    # the definition recovered from the Rigid Body Marker columns puts the template on the
    # measured labelled markers: 0.06 mm median, 0.09 mm at worst on this take (Motive's
    # fitted markers sit that far from the raw ones: static-marker noise)
    R = matrix_from_quaternion(poses.quat_xyzw)
    placed = np.einsum("fij,kj->fki", R, body.offsets_m) + poses.xyz_m[:, None]
    err = np.linalg.norm(placed - take.labelled_m, axis=2)
    assert np.median(err) < 1e-4 and err.max() < 2e-4


def test_row_layout_definition_frames_and_markers():
    take = read_motive_csv(ROWS)
    assert take.meta["format_version"] == "1.1" and len(take.frame) == 548
    assert take.rate_hz == pytest.approx(120.0, rel=1e-5)
    (body,) = take.bodies
    assert (body.name, body.id) == ("Rigid Body 1", 1)
    assert body.offsets_m[0] == pytest.approx([-0.03673005, -0.03058720, 0.00660080])
    assert body.offsets_m.shape == (5, 3)
    poses = take.poses["Rigid Body 1"]
    assert poses.valid.sum() == 528 and not poses.valid[266:271].any()
    assert poses.quat_xyzw[0] == pytest.approx([0.43526953, -0.81957161, 0.15150657,
                                                0.34042403], abs=1e-7)
    # frame 0: four markers, labelled by the body; frame 266: two unlabelled ones
    assert np.isfinite(take.labelled_m[0]).all(axis=1).sum() == 4
    assert take.labelled_m[0, 0] == pytest.approx([0.02566679, 0.90468109, 0.67789614])
    assert np.isfinite(take.unlabelled_m[266]).all(axis=1).sum() == 2
    assert take.all_markers().shape[1] == len(take.labels) + take.unlabelled_m.shape[1]


@pytest.mark.parametrize("source", [MODERN, ROWS])
def test_written_take_reads_back(tmp_path, source):
    take = read_motive_csv(source)
    out = tmp_path / "take.csv"
    write_motive_csv(out, take, "roundtrip")
    back = read_motive_csv(out)
    assert back.meta["format_version"] == "1.23"
    assert back.labels == take.labels
    np.testing.assert_array_equal(back.frame, take.frame)
    for a, b in ((back.labelled_m, take.labelled_m), (back.unlabelled_m, take.unlabelled_m)):
        np.testing.assert_array_equal(np.isnan(a), np.isnan(b))
        assert np.nanmax(np.abs(a - b)) <= 5e-7 + 1e-12  # written to the micrometre
    for b0, b1 in zip(take.bodies, back.bodies, strict=True):
        assert (b1.name, b1.id) == (b0.name, b0.id)
        np.testing.assert_allclose(b1.offsets_m, b0.offsets_m, atol=2e-6)
        p0, p1 = take.poses[b0.name], back.poses[b0.name]
        np.testing.assert_array_equal(p1.valid, p0.valid)
        np.testing.assert_allclose(p1.xyz_m[p0.valid], p0.xyz_m[p0.valid], atol=5e-7)
        np.testing.assert_allclose(p1.quat_xyzw[p0.valid], p0.quat_xyzw[p0.valid], atol=2e-6)
    # Motive's column conventions: Type/Name/ID rows, a property row, then Frame,Time,axes
    rows = list(csv.reader(out.open()))
    assert rows[0][:2] == ["Format Version", "1.23"] and rows[1] == []
    assert [r[1] for r in rows[2:5]] == ["Type", "Name", "ID"]
    assert rows[6][:2] == ["Frame", "Time (Seconds)"]
    first = rows[2].index("Rigid Body")
    assert rows[5][first:first + 7] == ["Rotation"] * 4 + ["Position"] * 3
    assert rows[6][first:first + 7] == ["X", "Y", "Z", "W", "X", "Y", "Z"]


def test_euler_rotations_and_millimetres(tmp_path):
    """A modern file in millimetres with XYZ Euler angles, written by hand: rotations are
    intrinsic X then Y then Z (Motive's relative Euler order), i.e. R = Rx Ry Rz."""
    from scipy.spatial.transform import Rotation

    angles = np.array([[10.0, -20.0, 30.0], [45.0, 5.0, -60.0]])
    lines = ["Format Version,1.23,Take Name,t,Export Frame Rate,100.000000,Rotation Type,XYZ,"
             "Length Units,Millimeters,Coordinate Space,Global", "",
             ",Type,Rigid Body,Rigid Body,Rigid Body,Rigid Body,Rigid Body,Rigid Body,Marker,"
             "Marker,Marker",
             ",Name,rb,rb,rb,rb,rb,rb,Unlabeled 1,Unlabeled 1,Unlabeled 1",
             ",ID,7,7,7,7,7,7,1,1,1",
             ",,Rotation,Rotation,Rotation,Position,Position,Position,Position,Position,"
             "Position",
             "Frame,Time (Seconds),X,Y,Z,X,Y,Z,X,Y,Z"]
    for f, a in enumerate(angles):
        lines.append(f"{f},{f / 100:.6f},{a[0]},{a[1]},{a[2]},100,200,300,1000,,")
    path = tmp_path / "euler.csv"
    path.write_text("\n".join(lines) + "\n")
    take = read_motive_csv(path)
    poses = take.poses["rb"]
    expect = Rotation.from_euler("XYZ", angles, degrees=True).as_quat()  # x y z w
    sign = np.sign(np.sum(expect * poses.quat_xyzw, axis=1, keepdims=True))
    np.testing.assert_allclose(poses.quat_xyzw * sign, expect, atol=1e-12)
    assert poses.xyz_m[0] == pytest.approx([0.1, 0.2, 0.3])
    assert take.bodies[0].id == 7 and len(take.bodies[0].offsets_m) == 0
    assert not np.isfinite(take.unlabelled_m).all(axis=2).any()  # only x was given


@pytest.mark.parametrize("text, message", [
    ("frame,x,y,z\n0,1,2,3\n", "is not a Motive CSV export"),
    ("Format Version,1.23,Length Units,Inches\n", "Length Units"),
    ("Format Version,1.23\n\n,Type,Marker\n", "no 'Frame,Time,...' header row"),
    ("Format Version,1.23\n\n,Type,Marker\n,Name,a\n,ID,1\n,,Position\nFrame,Time,X\n0,0,x\n",
     "bad.csv:8: 'x' in column 3 is not a number"),
    ("comment,x\nlefthanded\n", "left-handed"),
    ("comment,x\ntrackable,a,1\n", "bad.csv:2: a trackable definition row should be"),
    ("comment,x\ntrackable,a,1,2,0,0,0\n", "bad.csv:2: a trackable definition row"),
    ("comment,x\nframe,0,0.0,0,2,1,2,3,0\n", "bad.csv:2: a frame row should be"),
    ("comment,x\nframe,0,0.0,0,0\nbogus,1\n", "bad.csv:3: unknown row type"),
    ("Format Version,1.23,Rotation Type,XYX\n", "bad.csv:1: Rotation Type"),
    ("Format Version,1.23,Coordinate Space,Local\n", "Coordinate Space Global"),
    ("Format Version,1.23\n\n,Type,Marker\n,Name,a\n,ID,1\n,,Position\nFrame,Time,X,Y,Z\n"
     "0,0,1,2,3\n1,0.1,1,2,3,4,5\n", "bad.csv:9: 7 cells"),
    ("Format Version,1.23\n\n,Type,Marker\n,Name,a\n,ID,1\n,,Position\nFrame,Time,X,Y,Z\n"
     "0,0,1,2,3\n\n1,0.1,1,y,3\n", "bad.csv:10: 'y' in column 4 is not a number"),
    ("Format Version,1.23\n\n,Type,Marker,Marker\n,Name,a,a\n,ID,1,1\n,,Position,Position\n"
     "Frame,Time,X,Y\n0,0,1,2\n", "bad.csv:7: 'a' has no Z column"),
    ("comment,x\ninfo,version,1.1\n", "no 'frame' rows"),
    ("comment,x\nframe,0,0.0,1,1,2\n", "a frame row should be"),
])
def test_what_is_not_a_readable_export_is_one_clear_error(tmp_path, text, message):
    path = tmp_path / "bad.csv"
    path.write_text(text)
    with pytest.raises(UserError, match=message.replace("(", r"\(").replace(")", r"\)")
                       .replace(".", r"\.")):
        read_motive_csv(path)


# ---- every layout, from small files written by hand from the published layouts ----------

def known_take(n_frames=4, seed=3):
    """Two bodies with known templates and poses, a frame where body 2 is not tracked, and
    one stray marker: (templates, positions (F, B, 3), rotations (F, B) scipy Rotations,
    tracked (F, B), world markers (F, B, K, 3), stray (F, 3))."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed)
    templates = [np.array([[0.05, 0.0, 0.0], [-0.03, 0.04, 0.0], [0.0, -0.05, 0.02]]),
                 np.array([[0.06, 0.01, 0.0], [-0.04, 0.05, 0.01], [0.0, -0.07, 0.0],
                           [0.02, 0.02, 0.05]])]
    pos = rng.uniform(-1, 1, (n_frames, 2, 3)) + [0, 1.0, 0]
    rots = [[Rotation.from_rotvec(rng.normal(0, 1.0, 3)) for _ in range(2)]
            for _ in range(n_frames)]
    tracked = np.ones((n_frames, 2), bool)
    tracked[2, 1] = False
    world = [[rots[f][b].apply(templates[b]) + pos[f, b] for b in range(2)]
             for f in range(n_frames)]
    stray = rng.uniform(-2, 2, (n_frames, 3))
    return templates, pos, rots, tracked, world, stray


def _fmt(values) -> list[str]:
    return [f"{v:.8f}" for v in values]


def write_rows_layout(path, version: str):
    """A format 1.0 (trackable rows, markers x y z id) or 1.1 (rigidbody rows, markers
    x y z id name) file, as the files' own comment rows describe them."""
    templates, pos, rots, tracked, world, stray = known_take()
    kind = "trackable" if version == "1.0" else "rigidbody"
    lines = ['comment,"NaturalPoint Export Data"', 'comment,"== written by hand"',
             "righthanded"]
    if version != "1.0":
        lines.append(f"info,version,{version}")
    lines += [f"info,framecount,{len(pos)}", f"info,{kind}count,2"]
    for b, name in enumerate(["rb1", "rb2"]):
        lines.append(",".join([kind, f'"{name}"', str(b + 1), str(len(templates[b]))]
                              + _fmt(templates[b].ravel())))
    for f in range(len(pos)):
        row = ["frame", str(f), f"{f / 100:.8f}", str(int(tracked[f].sum()))]
        for b in np.flatnonzero(tracked[f]):
            q = rots[f][b].as_quat()
            yaw, pitch, roll = rots[f][b].as_euler("YXZ", degrees=True)
            row += [str(b + 1)] + _fmt(pos[f, b]) + _fmt(q) + _fmt([yaw, pitch, roll])
        markers = [(world[f][b][k], b, k) for b in range(2) for k in range(len(templates[b]))
                   if tracked[f, b]] + [(stray[f], -1, -1)]
        row.append(str(len(markers)))
        for xyz, b, k in markers:
            row += _fmt(xyz) + ["0"]
            if version != "1.0":
                row.append(f"rb{b + 1}-Marker {k + 1}" if b >= 0 else f"Marker-{1700 + f}")
        lines.append(",".join(row))
        for b in range(2):  # the extended per-frame row: read past, not used
            k = len(templates[b])
            lines.append(",".join([kind, str(f), f"{f / 100:.8f}", f'"rb{b + 1}"', str(b + 1),
                                   "0", str(k)] + _fmt(world[f][b].ravel())
                                  + ["NAN"] * (3 * k) + ["1"] * k + ["1.0"] * k + ["0.0001"]))
    path.write_text("\n".join(lines) + "\n")


@pytest.mark.parametrize("version", ["1.0", "1.1"])
def test_row_layouts_written_by_hand_read_as_written(tmp_path, version):
    templates, pos, rots, tracked, world, stray = known_take()
    path = tmp_path / f"v{version}.csv"
    write_rows_layout(path, version)
    take = read_motive_csv(path)
    assert take.meta["format_version"] == version and take.up_axis == "y"
    assert [(b.name, b.id) for b in take.bodies] == [("rb1", 1), ("rb2", 2)]
    for b, body in enumerate(take.bodies):
        np.testing.assert_allclose(body.offsets_m, templates[b], atol=1e-8)
        poses = take.poses[body.name]
        np.testing.assert_array_equal(poses.valid, tracked[:, b])
        v = tracked[:, b]
        np.testing.assert_allclose(poses.xyz_m[v], pos[v, b], atol=1e-8)
        q = np.array([rots[f][b].as_quat() for f in np.flatnonzero(v)])
        np.testing.assert_allclose(poses.quat_xyzw[v], q, atol=2e-8)
    # every marker of the frame, in the file's order: 1.0 markers carry no name, so all
    # are unlabelled; 1.1 names the body's markers, the stray stays unlabelled
    for f in range(len(pos)):
        seen = take.all_markers()[f]
        seen = seen[np.isfinite(seen).all(axis=1)]
        want = np.concatenate([world[f][b] for b in range(2) if tracked[f, b]] + [stray[f:f + 1]])
        key = np.lexsort(want.T)
        np.testing.assert_allclose(seen[np.lexsort(seen.T)], want[key], atol=1e-8)
    if version == "1.0":
        assert take.labels == [] and take.labelled_m.shape[1] == 0
    else:
        assert take.labels[:3] == ["rb1:Marker1", "rb1:Marker2", "rb1:Marker3"]
        np.testing.assert_allclose(take.labelled_m[0, 0], world[0][0][0], atol=1e-8)


TABLE_CASES = [  # (Format Version, Rotation Type, Length Units, labels in column 2, up axis)
    ("1.2", "Quaternion", None, False, None),
    ("1.21", "XYZ", "Millimeters", False, None),
    ("1.22", "XZY", "Centimeters", True, "z"),
    ("1.23", "YXZ", "Meters", True, None),
    ("1.23", "YZX", "Millimeters", True, None),
    ("1.24", "ZXY", "Meters", True, "z"),
    ("1.24", "ZYX", "Centimeters", True, None),
    ("1.25", "Quaternion", "Millimeters", True, "z"),
]


def write_table_layout(path, version, rotation, units, labelled_rows):
    """A table export as NaturalPoint's CSV page describes it: per body Rotation (X Y Z W,
    or X Y Z degrees about the body's moving axes in the Rotation Type's order), Position,
    Mean Marker Error, then rb1's Rigid Body Marker columns, labelled and unlabelled markers."""
    templates, pos, rots, tracked, world, stray = known_take()
    scale = {None: 1.0, "Meters": 1.0, "Centimeters": 100.0, "Millimeters": 1000.0}[units]
    props = ["Format Version", version, "Take Name", "hand", "Export Frame Rate", "100",
             "Rotation Type", rotation]
    if units:
        props += ["Length Units", units]
    props += ["Coordinate Space", "Global"]
    typ, name, ident, prop, axis = [], [], [], [], []
    cols = []

    def add(t, n, i, p, axes, values):
        for a, col in zip(axes, np.asarray(values).T, strict=True):
            typ.append(t), name.append(n), ident.append(str(i)), prop.append(p), axis.append(a)
            cols.append(col)

    for b in range(2):
        v = tracked[:, b]
        if rotation == "Quaternion":
            rot = np.array([rots[f][b].as_quat() for f in range(len(pos))])
            add("Rigid Body", f"rb{b + 1}", b + 1, "Rotation", "XYZW", rot)
        else:
            seq = np.array([rots[f][b].as_euler(rotation, degrees=True) for f in range(len(pos))])
            add("Rigid Body", f"rb{b + 1}", b + 1, "Rotation", "XYZ",
                seq[:, [rotation.index(a) for a in "XYZ"]])
        cols_from = len(cols)
        add("Rigid Body", f"rb{b + 1}", b + 1, "Position", "XYZ", pos[:, b] * scale)
        add("Rigid Body", f"rb{b + 1}", b + 1, "Mean Marker Error", [""],
            np.full((len(pos), 1), 0.0001 * scale))
        for c in range(cols_from - (4 if rotation == "Quaternion" else 3), len(cols)):
            cols[c] = np.where(v, cols[c], np.nan)
    for k in range(3):
        add("Rigid Body Marker", f"rb1:Marker{k + 1}", 1, "Position", "XYZ",
            np.array([world[f][0][k] for f in range(len(pos))]) * scale)
    for k in range(3):
        add("Marker", f"rb1:Marker{k + 1}", f"1{k}", "Position", "XYZ",
            np.array([world[f][0][k] for f in range(len(pos))]) * scale)
    add("Marker", "Unlabeled 1000", "U1", "Position", "XYZ", stray * scale)
    label = ["Type", "Name", "ID", ""] if labelled_rows else [""] * 4
    lines = [",".join(props), ""]
    for lab, row in zip(label, (typ, name, ident, prop), strict=True):
        lines.append(",".join(["", lab] + row))
    lines.append(",".join(["Frame", "Time (Seconds)"] + axis))
    values = np.column_stack(cols)
    for f in range(len(pos)):
        cells = ["" if not np.isfinite(x) else f"{x:.6f}" for x in values[f]]
        lines.append(",".join([str(f), f"{f / 100:.6f}"] + cells))
    path.write_text("\n".join(lines) + "\n")


@pytest.mark.parametrize("version, rotation, units, labelled_rows, up", TABLE_CASES)
def test_table_layouts_written_by_hand_read_as_written(tmp_path, version, rotation, units,
                                                      labelled_rows, up):
    templates, pos, rots, tracked, world, stray = known_take()
    path = tmp_path / "table.csv"
    write_table_layout(path, version, rotation, units, labelled_rows)
    take = read_motive_csv(path, up_axis=up)
    assert take.meta["format_version"] == version and take.up_axis == (up or "y")
    assert take.meta["rotation"] == rotation.upper()
    step = {None: 1e-6, "Meters": 1e-6, "Centimeters": 1e-8, "Millimeters": 1e-9}[units]
    assert [(b.name, b.id) for b in take.bodies] == [("rb1", 1), ("rb2", 2)]
    for b, body in enumerate(take.bodies):
        poses = take.poses[body.name]
        np.testing.assert_array_equal(poses.valid, tracked[:, b])
        v = tracked[:, b]
        np.testing.assert_allclose(poses.xyz_m[v], pos[v, b], atol=step)
        np.testing.assert_allclose(poses.error_m[v], 0.0001, atol=step)
        want = np.array([rots[f][b].as_quat() for f in np.flatnonzero(v)])
        sign = np.sign(np.sum(want * poses.quat_xyzw[v], axis=1, keepdims=True))
        np.testing.assert_allclose(poses.quat_xyzw[v] * sign, want, atol=2e-6)
    # rb1's definition from its Rigid Body Marker columns and Motive's poses
    np.testing.assert_allclose(take.bodies[0].offsets_m, templates[0], atol=20 * step)
    assert take.labels == ["rb1:Marker1", "rb1:Marker2", "rb1:Marker3"]
    np.testing.assert_allclose(take.labelled_m[:, 1], [w[0][1] for w in world], atol=step)
    np.testing.assert_allclose(take.unlabelled_m[:, 0], stray, atol=step)


def test_written_table_records_its_up_axis_and_reads_back(tmp_path):
    """A take turned to z-up and written says so (Up Axis,Z); read back it is z-up, and
    turned back to y-up it is the take as read."""
    from daemon.formats.motive_take import from_z_up, to_z_up

    path = tmp_path / "v1.1.csv"
    write_rows_layout(path, "1.1")
    take = read_motive_csv(path)
    z = to_z_up(take)
    # Motive's y (up) is mocapd's z; Motive's z (towards the viewer) is mocapd's -y
    np.testing.assert_allclose(z.labelled_m[..., 2], take.labelled_m[..., 1])
    np.testing.assert_allclose(z.labelled_m[..., 1], -take.labelled_m[..., 2])
    out = tmp_path / "z.csv"
    write_motive_csv(out, z, "z")
    assert "Up Axis,Z" in out.read_text().splitlines()[0]
    back = read_motive_csv(out)
    assert back.up_axis == "z"
    again = from_z_up(back, "y")
    for name, p in take.poses.items():
        q = again.poses[name]
        np.testing.assert_allclose(q.xyz_m[p.valid], p.xyz_m[p.valid], atol=1e-6)
        sign = np.sign(np.sum(q.quat_xyzw * p.quat_xyzw, axis=1, keepdims=True))[p.valid]
        np.testing.assert_allclose(q.quat_xyzw[p.valid] * sign, p.quat_xyzw[p.valid],
                                   atol=2e-6)
