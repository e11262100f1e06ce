"""C3D, CSV and BVH reading and writing, on the real CMU takes in fixtures/cmu_c3d."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from calibkit.core.errors import UserError
from daemon.formats.c3dio import (
    Points,
    Take,
    euler_zxy_matrix,
    read_bvh,
    read_c3d,
    read_labelled_csv,
    read_points,
    read_points_csv,
    read_take,
    write_bvh,
    write_c3d,
    write_labelled_csv,
    write_points_csv,
    zxy_euler_deg,
)

DATA = Path(__file__).resolve().parent.parent / "fixtures" / "cmu_c3d"


@pytest.fixture(scope="module")
def take_85():
    return read_c3d(DATA / "85_02.c3d")


def test_reads_85_02_in_metres(take_85):
    t = take_85
    assert t.xyz_m.shape == (810, 41, 3)
    assert t.rate_hz == 120.0
    assert t.labels[0] == "LFWT" and "Male:" not in "".join(t.labels)
    # first sample of LFWT as stored in the file (millimetres, float): 116.398, 1075.617
    assert t.xyz_m[0, 0, :2] == pytest.approx([0.116398, 1.075617], abs=1e-6)
    assert t.visible.all()


def test_reads_malformed_01_01_header():
    # The header says 1 analog sample per frame, ANALOG:RATE/POINT:RATE says 5; there are
    # no analog channels, so the points are read as they are.
    t = read_c3d(DATA / "01_01.c3d")
    assert t.xyz_m.shape == (2751, 42, 3)
    rbac = t.index("RBAC")
    assert (~t.visible[:, rbac]).sum() == 30 and not t.visible[-30:, rbac].any()
    dup = t.index("RBAC-1")
    seen = np.nonzero(t.visible[:, dup])[0]
    assert len(seen) == 8 and seen[-1] - seen[0] == 7
    # the duplicate lies within a few millimetres of RBAC, as SOURCE.txt says
    gap = np.linalg.norm(t.xyz_m[seen, dup] - t.xyz_m[seen, rbac], axis=1)
    assert gap.max() < 0.006


def test_truncated_and_foreign_files_give_user_errors(tmp_path):
    data = (DATA / "85_02.c3d").read_bytes()
    cut = tmp_path / "cut.c3d"
    cut.write_bytes(data[: len(data) // 2])
    with pytest.raises(UserError, match="truncated"):
        read_c3d(cut)
    junk = tmp_path / "junk.c3d"
    junk.write_bytes(b"not a c3d file at all" * 40)
    with pytest.raises(UserError, match="not a C3D"):
        read_c3d(junk)
    bad = bytearray(data)
    bad[2:4] = (99).to_bytes(2, "little")        # header point count != POINT:USED
    other = tmp_path / "bad.c3d"
    other.write_bytes(bytes(bad))
    with pytest.raises(UserError, match="inconsistent"):
        read_c3d(other)


def test_c3d_round_trip_keeps_gaps(tmp_path, take_85):
    t = Take(take_85.labels, take_85.xyz_m[:50].copy(), take_85.rate_hz, 1)
    t.xyz_m[10:20, 3] = np.nan
    t.filled[30:35, 5] = True                 # made-up samples: residual 0 in the file
    write_c3d(tmp_path / "a.c3d", t)
    back = read_c3d(tmp_path / "a.c3d")
    assert back.labels == t.labels and back.rate_hz == t.rate_hz
    assert np.array_equal(back.visible, t.visible)
    assert np.array_equal(back.filled, t.filled)
    # float32 millimetres: ~1e-4 mm rounding at metre scale
    assert np.nanmax(np.abs(back.xyz_m - t.xyz_m)) < 1e-6


def test_labelled_csv_round_trip_with_filled_flags(tmp_path, take_85):
    t = Take(take_85.labels[:5], take_85.xyz_m[:30, :5].copy(), 120.0, 7)
    t.xyz_m[3:6, 2] = np.nan
    t.filled[8:10, 1] = True
    write_labelled_csv(tmp_path / "a.csv", t)
    back = read_take(tmp_path / "a.csv")
    assert back.rate_hz == 120.0 and back.first_frame == 7
    assert np.array_equal(back.visible, t.visible)
    assert np.array_equal(back.filled, t.filled)
    assert np.nanmax(np.abs(back.xyz_m - t.xyz_m)) < 1e-6


def test_points_csv_accepts_triangulate_columns(tmp_path):
    p = tmp_path / "pts.csv"
    p.write_text("frame,x,y,z,reproj_px,ray_mm,n_cameras\n0,1,2,3,0.1,0.2,3\n"
                 "0,4,5,6,0.1,0.2,2\n1,7,8,9,0.3,0.1,4\n")
    pts = read_points_csv(p)
    assert pts.frame.tolist() == [0, 0, 1]
    assert pts.xyz_m[2].tolist() == [7, 8, 9]
    (tmp_path / "bad.csv").write_text("frame,x,y\n0,1,2\n")
    with pytest.raises(UserError, match="missing column"):
        read_points_csv(tmp_path / "bad.csv")
    (tmp_path / "nan.csv").write_text("frame,x,y,z\n0,1,oops,3\n")
    with pytest.raises(UserError, match="non-numeric"):
        read_points_csv(tmp_path / "nan.csv")


def test_points_from_take_shuffle_and_round_trip(tmp_path, take_85):
    t = Take(take_85.labels, take_85.xyz_m[:5], 120.0, 1)
    pts = Points.from_take(t, seed=3)
    assert len(pts.frame) == 5 * 41
    frames, per = pts.split()
    assert frames.tolist() == [1, 2, 3, 4, 5]
    # the same points, in another order
    assert not np.array_equal(per[0], t.xyz_m[0])
    assert np.allclose(np.sort(per[0], axis=0), np.sort(t.xyz_m[0], axis=0))
    write_points_csv(tmp_path / "p.csv", pts)
    back = read_points(tmp_path / "p.csv")
    assert np.abs(back.xyz_m - pts.xyz_m).max() < 1e-6


def test_euler_round_trip():
    rng = np.random.default_rng(0)
    ang = rng.uniform([-170, -80, -170], [170, 80, 170], (200, 3))
    R = euler_zxy_matrix(ang)
    assert np.allclose(zxy_euler_deg(R), ang, atol=1e-9)
    assert np.allclose(R @ np.swapaxes(R, 1, 2), np.eye(3), atol=1e-12)


def test_bvh_round_trip(tmp_path):
    rng = np.random.default_rng(1)
    names = ["hips", "spine", "head", "leg"]
    parents = [-1, 0, 1, 0]
    offsets = np.array([[0, 0, 0], [0, 0, 0.2], [0, 0, 0.3], [0, 0.1, -0.1]])
    ang = rng.uniform(-60, 60, (7, 4, 3))
    pos = rng.normal(0, 1, (7, 3))
    write_bvh(tmp_path / "m.bvh", names, parents, offsets, pos, euler_zxy_matrix(ang), 120.0)
    n2, p2, o2, motion = read_bvh(tmp_path / "m.bvh")
    assert n2 == names and p2 == parents
    assert np.allclose(o2, offsets, atol=1e-6)
    assert np.allclose(motion[:, :3] / 100.0, pos, atol=1e-6)
    assert np.allclose(motion[:, 3:].reshape(7, 4, 3), ang, atol=1e-4)


def test_read_take_rejects_unknown_suffix(tmp_path):
    (tmp_path / "a.trc").write_text("x")
    with pytest.raises(UserError, match="c3d or .csv"):
        read_take(tmp_path / "a.trc")
    with pytest.raises(UserError, match="cannot read"):
        read_labelled_csv(tmp_path / "missing.csv")
    with pytest.raises(UserError, match="does not exist"):
        read_take(tmp_path / "missing.c3d")
