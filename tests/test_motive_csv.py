"""Motive CSV: both layouts read from real exports, the modern one written and read back."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest

from calibkit.core.errors import UserError
from daemon.markers.motive_csv import read_motive_csv, write_motive_csv
from daemon.rigid import matrix_from_quaternion

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
     "not a number"),
    ("comment,x\nlefthanded\n", "left-handed"),
    ("comment,x\ntrackable,a,1\n", "'trackable' rows"),
    ("comment,x\ninfo,version,1.1\n", "no 'frame' rows"),
    ("comment,x\nframe,0,0.0,1,1,2\n", "a frame row should be"),
])
def test_what_is_not_a_readable_export_is_one_clear_error(tmp_path, text, message):
    path = tmp_path / "bad.csv"
    path.write_text(text)
    with pytest.raises(UserError, match=message.replace("(", r"\(").replace(")", r"\)")
                       .replace(".", r"\.")):
        read_motive_csv(path)
