"""`mocapd track` on a points CSV in windows (daemon/analysis/track_stream.py): the poses of
the whole take tracked at once, pose for pose, with window edges inside occlusions, inside
a run of frames missing from the file and while the bodies move; and against the truth."""

from __future__ import annotations

import json

import numpy as np
import pytest
from test_track import RATE, body_defs, capture, predicted_rms, write_config

from daemon.analysis import track_stream
from daemon.analysis.offline_track import (
    CloudTracker,
    cloud_from_points,
    figures,
    rotation_difference_deg,
    track_cloud,
)
from daemon.analysis.point_tracks import PointTracker, associate
from daemon.analysis.track_file import pose_table
from daemon.analysis.track_stream import Spool, track_spool, windows
from daemon.formats.c3dio import Points, read_points_csv, write_points_csv
from daemon.formats.points_csv import stream_points_csv
from daemon.formats.trajectory_io import read_poses_csv, write_poses_csv
from daemon.tracking.rigid import RigidConfig, quaternion_xyzw

GAP = range(300, 312)  # frames missing from the file: nothing seen at all


@pytest.fixture(scope="module")
def take(tmp_path_factory):
    """A simulated take written as a points CSV in frame order (as triangulate writes it),
    each frame's points shuffled: four moving bodies, 0.5 mm noise, 8 % of marker-frames
    hidden in 0.1-1 s spans, two strays a frame, frames 300-311 absent."""
    pts, bodies, visible = capture(n_frames=900, noise_m=0.0005, hidden=0.08, seed=7)
    keep = np.flatnonzero(~np.isin(pts.frame, list(GAP)))
    keep = keep[np.argsort(pts.frame[keep] + np.random.default_rng(8).random(len(keep)))]
    src = tmp_path_factory.mktemp("windows") / "points.csv"
    write_points_csv(src, Points(pts.frame[keep], pts.xyz_m[keep]))
    return src, bodies, visible


def _spool(src, folder):
    spool = Spool(folder)
    stream_points_csv(src, spool)
    return spool.finish()


def test_tracks_in_windows_are_the_whole_takes(take):
    src, bodies, _ = take
    cloud = cloud_from_points(read_points_csv(src), RATE)
    whole = associate(cloud.xyz, cloud.counts(), cloud.frame)
    parts = PointTracker()
    got = [parts.window(cloud.xyz[a:b], cloud.counts()[a:b], cloud.frame[a:b])
           for a, b in ((0, 1), (1, 250), (250, 300), (300, 301), (301, len(cloud)))]
    np.testing.assert_array_equal(np.concatenate([np.diff(g.start) for g in got]),
                                  np.diff(whole.start))  # the same tracks in each frame
    for name in ("ids", "xyz", "seen", "missing"):
        np.testing.assert_array_equal(np.concatenate([getattr(g, name) for g in got]),
                                      getattr(whole, name))


@pytest.mark.parametrize("window_points", [1, 97, "gap", 4000])
def test_windowed_run_writes_the_whole_takes_poses(take, tmp_path, window_points):
    """Byte for byte the poses file of the whole take tracked at once, whatever the
    windows (1 point: every frame its own window; "gap": the first window ends where the
    frames missing from the file begin)."""
    src, bodies, visible = take
    defs = body_defs(bodies)
    cloud = cloud_from_points(read_points_csv(src), RATE)
    whole = track_cloud(cloud, defs, RigidConfig(refine=False))
    write_poses_csv(tmp_path / "whole.csv", pose_table(whole), "note")
    with _spool(src, tmp_path) as spool:
        at_gap = window_points in (1, "gap")
        if window_points == "gap":
            window_points = int(spool.starts[np.searchsorted(spool.frames, GAP.stop)])
        edges = [a for a, _ in windows(spool.starts, window_points)][1:]
        figs, used = track_spool(spool, RATE, defs, RigidConfig(), 30.0, 20.0,
                                 tmp_path / "windows.csv", "note",
                                 window_points=window_points)
    assert used == defs  # the definitions fit: nothing refined
    assert (tmp_path / "windows.csv").read_bytes() == (tmp_path / "whole.csv").read_bytes()
    want = figures(whole)  # the figures too, but what refining did (nothing here)
    for b in figs["bodies"].values():
        assert b.pop("refine") == {"frames_used": 0, "applied": False}
    assert {k: v for k, v in figs.items() if k in want} == want
    assert figs["windows"] == len(edges) + 1 > 1
    assert not list(tmp_path.glob("*.spool")) and not list(tmp_path.glob("*.tmp"))

    # where the edges fell: in occlusions, in the missing frames, on moving bodies
    edge_frames = cloud.frame[edges]
    occluded = ~visible[edge_frames - 1] & ~visible[edge_frames]
    assert occluded.any(), "no edge inside an occlusion"
    if at_gap:
        assert any(cloud.frame[e - 1] < GAP.start and cloud.frame[e] >= GAP.stop
                   for e in edges)
    speed = [np.linalg.norm(b.poses[edge_frames, :3, 3] - b.poses[edge_frames - 1, :3, 3],
                            axis=1) * RATE for b in bodies]
    assert np.median(speed) > 0.05  # m/s: the bodies move across the edges


def test_windowed_poses_against_the_truth(take, tmp_path, mocapd_cli, monkeypatch):
    """The command, in windows of about 30 frames: poses within 1.3x of what a
    least-squares fit of the visible markers predicts under the noise, none off by 2 cm,
    and every frame with enough markers to start a body posed."""
    src, bodies, visible = take
    monkeypatch.setattr(track_stream, "WINDOW_POINTS", 500)
    out = tmp_path / "poses.csv"
    r = mocapd_cli("track", src, "--bodies", write_config(tmp_path / "m.toml", bodies),
                   "--rate", RATE, "--out", out, "--json", tmp_path / "f.json")
    assert r.code == 0, r.err
    figs = json.loads((tmp_path / "f.json").read_text())
    assert figs["windows"] > 20 and figs["frames"] == 900 - len(GAP)
    assert figs["input"]["bad_rows"]["skipped"] == 0
    table = read_poses_csv(out)
    frames = np.setdiff1d(np.arange(900), list(GAP))
    np.testing.assert_array_equal(table.frame, frames)
    start = 0
    for b, body in enumerate(bodies):
        k = len(body.markers_body)
        vis = visible[frames, start:start + k]
        start += k
        v = table.valid[:, b]
        enough = vis.sum(axis=1) >= min(k, 4)
        assert v[5:][enough[5:]].mean() > 0.99, body.name
        truth = body.poses[frames[v]]
        dp = np.linalg.norm(table.xyz[v, b] - truth[:, :3, 3], axis=1)
        da = np.radians(rotation_difference_deg(table.quat[v, b],
                                                quaternion_xyzw(truth[:, :3, :3])))
        want_p, want_a = predicted_rms(body, vis[v], 0.0005)
        assert np.sqrt(np.mean(dp ** 2)) < 1.3 * want_p, body.name
        assert np.sqrt(np.mean(da ** 2)) < 1.3 * want_a, body.name
        assert dp.max() < 0.02


def test_a_file_out_of_frame_order_is_tracked_whole_with_a_note(take, tmp_path, mocapd_cli):
    """Frames 0-99 moved to the end of the file: no window can hold whole frames, so the
    take is tracked whole (as before windows), sorted by frame, and the user told."""
    src, bodies, _ = take
    lines = src.read_text().splitlines(keepends=True)
    late = [ln for ln in lines[1:] if int(ln.split(",")[0]) >= 100]
    moved = tmp_path / "moved.csv"
    moved.write_text("".join([lines[0], *late, *lines[1:len(lines) - len(late)]]))
    config = write_config(tmp_path / "m.toml", bodies)
    runs = {}
    for name, path in (("sorted", src), ("moved", moved)):
        r = mocapd_cli("track", path, "--bodies", config, "--rate", RATE, "--out",
                       tmp_path / f"{name}.poses.csv")
        assert r.code == 0, r.err
        runs[name] = r
    assert "frame numbers go back" in runs["moved"].err
    assert "frame numbers go back" not in runs["sorted"].err
    a, b = (read_poses_csv(tmp_path / f"{n}.poses.csv") for n in ("sorted", "moved"))
    np.testing.assert_array_equal(a.valid, b.valid)
    np.testing.assert_array_equal(a.xyz, b.xyz)


def test_windows_hold_whole_frames_within_the_bound():
    starts = np.array([0, 3, 10, 11, 30, 31, 35])  # frame rows hold 3, 7, 1, 19, 1, 4 points
    got = list(windows(starts, 10))
    assert got == [(0, 2), (2, 3), (3, 4), (4, 6)]
    assert list(windows(starts, 1)) == [(k, k + 1) for k in range(6)]
    assert list(windows(starts, 100)) == [(0, 6)]


def test_cloud_tracker_in_windows_is_update_frame_by_frame(take):
    """Bit for bit: windows of the batched tracker against the whole take sent through
    RigidTracker.update() frame by frame."""
    src, bodies, _ = take
    defs = body_defs(bodies)
    cloud = cloud_from_points(read_points_csv(src), RATE)
    slow = track_cloud(cloud, defs, batched=False)
    tracker = CloudTracker(defs)
    parts = []
    for a, b in ((0, 37), (37, 38), (38, 299), (299, 500), (500, len(cloud))):
        sub = type(cloud)(cloud.frame[a:b], cloud.t_s[a:b], cloud.xyz[a:b])
        parts.append(tracker.window(sub))
    for name in ("valid", "position", "quaternion", "error_m", "n_markers"):
        np.testing.assert_array_equal(np.concatenate([getattr(p, name) for p in parts]),
                                      getattr(slow, name))


def test_y_up_take_in_windows_is_the_whole_take_run(take, tmp_path, mocapd_cli, monkeypatch):
    """`--up-axis y` turns each window as the whole-take path turns the take: the poses
    written in windows are those of the same command made to run whole (--motive-out
    needs the whole take), to the 1e-7 m and 1e-8 the file holds."""
    src, bodies, _ = take
    monkeypatch.setattr(track_stream, "WINDOW_POINTS", 700)
    config = write_config(tmp_path / "m.toml", bodies)  # a body's own frame does not turn
    out = {}
    for name, extra in (("windows", ()), ("whole", ("--motive-out", tmp_path / "m.csv"))):
        out[name] = tmp_path / f"{name}.csv"
        r = mocapd_cli("track", src, "--bodies", config, "--rate", RATE, "--up-axis", "y",
                       "--out", out[name], "--json", tmp_path / f"{name}.json", *extra)
        assert r.code == 0, r.err
    figs = {n: json.loads((tmp_path / f"{n}.json").read_text()) for n in out}
    assert figs["windows"]["windows"] > 20 and "windows" not in figs["whole"]
    assert figs["windows"]["input"]["up_axis"] == figs["whole"]["input"]["up_axis"] == "y"
    a, b = (read_poses_csv(out[n]) for n in ("windows", "whole"))
    np.testing.assert_array_equal(a.valid, b.valid)
    assert a.valid.mean() > 0.9
    np.testing.assert_allclose(a.xyz[a.valid], b.xyz[b.valid], rtol=0, atol=1.5e-7)
    np.testing.assert_allclose(a.quat[a.valid], b.quat[b.valid], rtol=0, atol=1.5e-8)
    assert out["windows"].read_text().splitlines()[0] == out["whole"].read_text().splitlines()[0]
