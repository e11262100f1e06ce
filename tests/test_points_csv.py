"""Points CSV reading (daemon/formats/points_csv.py) and what track and label say about it.

Bad rows are written by hand at known lines, so the counts, kinds and first line asserted
are read off the file; the streamed read is compared with the whole-file read of
daemon.formats.c3dio on simulated points, split into blocks that cut lines in two.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import tomli_w

from calibkit.core.errors import UserError
from calibkit.synthetic import sim
from daemon.formats import points_csv
from daemon.formats.c3dio import Points, read_points_csv, write_points_csv
from daemon.formats.points_csv import points_header
from daemon.formats.points_csv import read_points_csv as stream_points

BAD = """# rate_hz=100
# made by hand: lines 5-10 and 12 are bad, line 11 is blank
frame,x,y,z,reproj_px,cameras
0,0.1,0.2,0.3,0.5,cam0;cam1
1,nan,0.2,0.3,0.5,cam0
1,0.4,0.5
1,0.4,oops,0.6,0.5,cam0
2.5,0.1,0.2,0.3,0.5,cam1
2,0.1,-inf,0.3,0.5,cam1
2,,0.2,0.3,0.5,cam1

3,0.1,0.2,0.3,0.5,cam0,extra
3,0.7,0.8,0.9,0.1,"cam0,cam2"
4,1.0,1.1,1.2,0.2,cam1
"""


def test_bad_rows_counted_by_kind_with_the_first_line(tmp_path):
    path = tmp_path / "bad.csv"
    path.write_text(BAD)
    for block in (1 << 20, 16, 37):  # one block; lines cut across many blocks
        pts, bad = stream_points(path, block_bytes=block)
        assert pts.frame.tolist() == [0, 3, 4]
        assert pts.xyz_m.tolist() == [[0.1, 0.2, 0.3], [0.7, 0.8, 0.9], [1.0, 1.1, 1.2]]
        assert bad.rows == 10 and bad.count == 7
        assert bad.kinds == {"NaN or inf": 2, "wrong number of columns": 2,
                             "not a number": 2, "frame not a whole number": 1}
        assert bad.first_line == 5 and bad.first_kind == "NaN or inf"
    assert "skipped 7 of 10 rows" in bad.summary() and "line 5" in bad.summary()
    assert points_header(path).rate_hz == 100.0
    with pytest.raises(UserError, match=r"line 5: NaN or inf"):
        stream_points(path, strict=True)


def test_streaming_equals_the_whole_file_read(tmp_path):
    """Simulated points (with hidden markers), as `calibkit triangulate`-like files with
    extra columns and as our plain frame,x,y,z: the same points, bit for bit, from the
    whole-file reader and from the stream in blocks of every size."""
    truth, _ = sim.rigid_body_motion(3, 200, fps=100.0, seed=2)
    keep = np.random.default_rng(2).random(len(truth.frame)) > 0.1
    pts = Points(truth.frame[keep], truth.xyz[keep])
    plain = tmp_path / "plain.csv"
    write_points_csv(plain, pts)
    wide = tmp_path / "wide.csv"
    with open(wide, "w", encoding="utf-8") as handle:
        handle.write("frame,x,y,z,reproj_px,ray_mm,n_cameras,cameras\n")
        for f, (x, y, z) in zip(pts.frame, pts.xyz_m, strict=True):
            handle.write(f"{f},{x:.6f},{y:.6f},{z:.6f},0.2,1.5,3,cam0;cam3;cam4\n")
    for path in (plain, wide):
        whole = read_points_csv(path)
        for block in (1 << 20, 4096, 333):
            streamed, bad = stream_points(path, block_bytes=block)
            assert bad.count == 0 and bad.rows == len(pts.frame)
            assert np.array_equal(streamed.frame, whole.frame)
            assert np.array_equal(streamed.xyz_m, whole.xyz_m)
        assert np.abs(streamed.xyz_m - pts.xyz_m).max() < 1e-6  # the file keeps 1e-6 m
        assert np.array_equal(streamed.frame, pts.frame)


def test_windows_line_ends_and_a_byte_order_mark_read_as_any_other(tmp_path):
    """What a spreadsheet saves: CRLF line ends, a UTF-8 byte order mark, the z column
    last (so its value is followed by the CR)."""
    (tmp_path / "win.csv").write_bytes(b"\xef\xbb\xbfframe,x,y,z\r\n0,1.5,2,3\r\n"
                                       b"\r\n1,4,5,6.25\r\n")
    for block in (1 << 20, 9):
        pts, bad = stream_points(tmp_path / "win.csv", block_bytes=block)
        assert pts.frame.tolist() == [0, 1] and bad.count == 0
        assert pts.xyz_m.tolist() == [[1.5, 2.0, 3.0], [4.0, 5.0, 6.25]]


def test_files_that_hold_nothing_are_one_clear_error(tmp_path):
    cases = {"empty.csv": ("", "is empty"),
             "nohead.csv": ("# only a comment\n", "is empty"),
             "cols.csv": ("frame,x,y\n0,1,2\n", "missing column"),
             "allbad.csv": ("frame,x,y,z\n0,1,oops,3\n", "no usable points.*not a number"),
             "header.csv": ("frame,x,y,z\n", "holds no points"),
             "rate.csv": ("# rate_hz=fast\nframe,x,y,z\n0,1,2,3\n", "rate_hz")}
    for name, (text, match) in cases.items():
        (tmp_path / name).write_text(text)
        with pytest.raises(UserError, match=match):
            stream_points(tmp_path / name)
    (tmp_path / "bin.csv").write_bytes(b"\xff\xfe\x00frame")
    with pytest.raises(UserError, match="not a text CSV"):
        stream_points(tmp_path / "bin.csv")


@pytest.fixture()
def take_with_bad_rows(tmp_path):
    """Two bodies moving for 200 frames as a points CSV, with three bad rows put in at
    known lines (they replace nothing: every good point is still there)."""
    truth, bodies = sim.rigid_body_motion(2, 200, fps=100.0, markers_per_body=[4, 5],
                                          seed=3)
    write_points_csv(tmp_path / "good.csv", Points(truth.frame, truth.xyz))
    lines = (tmp_path / "good.csv").read_text().splitlines(keepends=True)
    lines.insert(10, "2,0.1,nan,0.3\n")  # becomes line 11
    lines.insert(50, "5,0.1,0.2\n")  # line 51
    lines.insert(400, "44,zero,0.2,0.3\n")  # line 401
    (tmp_path / "bad.csv").write_text("".join(lines))
    (tmp_path / "bodies.toml").write_text(tomli_w.dumps({"rigid_body": [
        {"name": b.name, "id": int(b.id), "markers": b.markers_body.tolist()}
        for b in bodies]}))
    return tmp_path


def test_track_warns_about_bad_rows_and_strict_refuses(take_with_bad_rows, mocapd_cli):
    d = take_with_bad_rows
    args = ("--bodies", d / "bodies.toml", "--rate", "100")
    r = mocapd_cli("track", d / "bad.csv", *args, "--out", d / "bad_poses.csv", "--json",
                   d / "bad.json")
    assert r.code == 0, r.err
    warning = [ln for ln in r.err.splitlines() if "skipped" in ln]
    assert len(warning) == 1
    assert "skipped 3 of" in warning[0] and "line 11 (NaN or inf)" in warning[0]
    figs = json.loads((d / "bad.json").read_text())
    assert figs["input"]["bad_rows"]["skipped"] == 3
    assert figs["input"]["bad_rows"]["first_line"] == 11
    assert figs["input"]["bad_rows"]["by_kind"] == {"NaN or inf": 1, "not a number": 1,
                                                    "wrong number of columns": 1}
    # the good rows are tracked as they are without the bad ones
    r = mocapd_cli("track", d / "good.csv", *args, "--out", d / "good_poses.csv")
    assert r.code == 0, r.err
    assert "skipped" not in r.err
    assert (d / "bad_poses.csv").read_text().splitlines()[1:] == \
        (d / "good_poses.csv").read_text().splitlines()[1:]
    r = mocapd_cli("track", d / "bad.csv", *args, "--out", d / "strict.csv", "--strict")
    assert r.code == 2 and len(r.err.strip().splitlines()) == 1
    assert "line 11" in r.err and "NaN or inf" in r.err
    assert not (d / "strict.csv").exists()


def test_track_asks_for_the_rate_before_reading(take_with_bad_rows, mocapd_cli, monkeypatch):
    def never(*_a, **_k):
        raise AssertionError("read the points before asking for --rate")

    monkeypatch.setattr(points_csv, "read_points_csv", never)
    d = take_with_bad_rows
    r = mocapd_cli("track", d / "good.csv", "--bodies", d / "bodies.toml", "--out",
                   d / "p.csv")
    assert r.code == 2 and "--rate" in r.err and len(r.err.strip().splitlines()) == 1


def test_label_warns_about_bad_rows_and_strict_refuses(tmp_path, mocapd_cli):
    from calibkit.synthetic import person
    from daemon.formats.c3dio import Take, read_labelled_csv
    from daemon.labelling.markerset import SHIPPED, MarkerSet

    ms = MarkerSet.load(SHIPPED / "sim_person.toml")
    walk = person.walk(120, 100.0, seed=5)
    take = Take(walk.labels, walk.markers_m, 100.0).select(ms.labels)
    write_points_csv(tmp_path / "p.csv", Points.from_take(take, seed=5))
    lines = (tmp_path / "p.csv").read_text().splitlines(keepends=True)
    lines.insert(7, "0,inf,1,2\n")  # line 8
    (tmp_path / "p.csv").write_text("".join(lines))
    r = mocapd_cli("label", tmp_path / "p.csv", "--markerset", "sim_person", "--rate", "100",
                   "--out", tmp_path / "lab.csv", "--json", tmp_path / "lab.json")
    assert r.code == 0, r.err
    warning = [ln for ln in r.err.splitlines() if "skipped" in ln]
    assert len(warning) == 1 and "skipped 1 of" in warning[0] and "line 8" in warning[0]
    assert json.loads((tmp_path / "lab.json").read_text())["bad_rows"]["skipped"] == 1
    back = read_labelled_csv(tmp_path / "lab.csv").select(ms.labels)
    assert np.nanmax(np.abs(back.xyz_m - take.xyz_m)) < 2e-6  # every good point labelled
    r = mocapd_cli("label", tmp_path / "p.csv", "--markerset", "sim_person", "--rate", "100",
                   "--out", tmp_path / "strict.csv", "--strict")
    assert r.code == 2 and len(r.err.strip().splitlines()) == 1 and "line 8" in r.err
    assert not (tmp_path / "strict.csv").exists()
