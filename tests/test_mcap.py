"""MCAP output with Foxglove's schemas: what `mocapd track --out x.mcap` writes is the
poses the CSV holds (and so the truth within the fit's error), the markers of each frame,
under the schema names Foxglove recognises; a file appears whole or not at all."""

from __future__ import annotations

import json

import numpy as np
import pytest
from mcap.reader import make_reader
from test_track import RATE, capture, write_config

from calibkit.core.errors import UserError
from daemon.analysis.offline_track import cloud_from_points
from daemon.formats.c3dio import read_points_csv, write_points_csv
from daemon.formats.trajectory_io import read_poses_csv
from daemon.publish.mcap_poses import McapPoseWriter


def read_mcap(path):
    """{topic: [(log_time_ns, schema name, message)]} and {topic: schema encoding}."""
    out, encodings = {}, {}
    with open(path, "rb") as f:
        for schema, channel, message in make_reader(f).iter_messages():
            assert channel.message_encoding == "json"
            encodings[channel.topic] = schema.encoding
            out.setdefault(channel.topic, []).append(
                (message.log_time, schema.name, json.loads(message.data)))
    return out, encodings


def test_track_to_mcap_holds_the_poses_and_markers(tmp_path, mocapd_cli):
    pts, bodies, _visible = capture(n_frames=300, noise_m=0.0005, seed=2)
    src = tmp_path / "points.csv"
    write_points_csv(src, pts)
    cfg = write_config(tmp_path / "m.toml", bodies)
    for out in (tmp_path / "poses.csv", tmp_path / "poses.mcap"):
        r = mocapd_cli("track", src, "--bodies", cfg, "--rate", RATE, "--out", out)
        assert r.code == 0, r.err
    table = read_poses_csv(tmp_path / "poses.csv")
    topics, encodings = read_mcap(tmp_path / "poses.mcap")
    assert set(encodings.values()) == {"jsonschema"}
    assert {s for msgs in topics.values() for _, s, _ in msgs} == {
        "foxglove.FrameTransforms", "foxglove.PoseInFrame", "foxglove.SceneUpdate"}

    for b, body in enumerate(bodies):
        msgs = topics[f"/mocap/{body.name}/pose"]
        v = table.valid[:, b]
        assert len(msgs) == v.sum() > 150  # occluded spans leave some frames without a pose
        t_ns = np.array([t for t, _, _ in msgs])
        np.testing.assert_allclose(t_ns, table.t_s[v] * 1e9, atol=1000)  # the CSV's 1 us
        xyz = np.array([[m["pose"]["position"][k] for k in "xyz"] for _, _, m in msgs])
        quat = np.array([[m["pose"]["orientation"][k] for k in "xyzw"] for _, _, m in msgs])
        np.testing.assert_allclose(xyz, table.xyz[v, b], atol=1e-7)  # the CSV's 0.1 um
        np.testing.assert_allclose(quat, table.quat[v, b], atol=1e-8)
        # and so the truth, within the fit's error
        err = np.linalg.norm(xyz - body.poses[v, :3, 3], axis=1)
        assert np.sqrt(np.mean(err ** 2)) < 0.002 and err.max() < 0.02
        assert all(m["frame_id"] == "world" for _, _, m in msgs)

    # /tf: one transform per valid body and frame, child frames named after the bodies
    tf = topics["/tf"]
    children = [t["child_frame_id"] for _, _, m in tf for t in m["transforms"]]
    assert len(children) == table.valid.sum()
    assert set(children) == {b.name for b in bodies}

    # /mocap/markers: every frame's finite points as spheres
    cloud = cloud_from_points(read_points_csv(src), RATE)  # the markers the command read
    scenes = topics["/mocap/markers"]
    assert len(scenes) == len(cloud)
    counts = [len(m["entities"][0]["spheres"]) for _, _, m in scenes]
    np.testing.assert_array_equal(counts, cloud.counts())
    first = np.array([[s["pose"]["position"][k] for k in "xyz"]
                      for s in scenes[0][2]["entities"][0]["spheres"]])
    want = cloud.xyz[0][np.isfinite(cloud.xyz[0]).all(axis=1)]
    np.testing.assert_allclose(np.sort(first, axis=0), np.sort(want, axis=0), atol=1e-9)


def test_writer_leaves_a_whole_file_or_none(tmp_path):
    path = tmp_path / "take.mcap"
    valid, xyz = np.array([True, False]), np.array([[0.1, 0.2, 0.3], [np.nan] * 3])
    quat = np.array([[0, 0, 0, 1.0], [np.nan] * 4])
    with pytest.raises(RuntimeError), McapPoseWriter(path, ["a", "b"]) as w:
        w.write(1_000, valid, xyz, quat)
        raise RuntimeError("the take failed half way")
    assert list(tmp_path.iterdir()) == []
    w = McapPoseWriter(path, ["a", "b"])
    w.write(1_000, valid, xyz, quat, np.array([[0.0, 0.0, 1.0], [np.nan] * 3]))
    w.abort()
    assert list(tmp_path.iterdir()) == []
    with McapPoseWriter(path, ["a", "b"]) as w:
        w.write(1_000, valid, xyz, quat, np.array([[0.0, 0.0, 1.0], [np.nan] * 3]))
    topics, _ = read_mcap(path)
    assert "/mocap/b/pose" not in topics  # no valid pose, no message
    assert topics["/mocap/a/pose"][0][2]["pose"]["position"] == {"x": 0.1, "y": 0.2, "z": 0.3}
    assert len(topics["/mocap/markers"][0][2]["entities"][0]["spheres"]) == 1
    assert [p.name for p in tmp_path.iterdir()] == ["take.mcap"]


def test_writer_refuses_what_it_cannot_name(tmp_path):
    with pytest.raises(UserError, match=r"\.mcap"):
        McapPoseWriter(tmp_path / "take.csv", ["a"])
    with pytest.raises(UserError, match="share a name"):
        McapPoseWriter(tmp_path / "take.mcap", ["a", "a"])


def test_track_refuses_other_output_kinds(tmp_path, mocapd_cli):
    pts, bodies, _ = capture(n_frames=20, seed=3)
    src = tmp_path / "points.csv"
    write_points_csv(src, pts)
    r = mocapd_cli("track", src, "--bodies", write_config(tmp_path / "m.toml", bodies),
                   "--rate", RATE, "--out", tmp_path / "poses.bag")
    assert r.code == 2 and ".csv or .mcap" in r.err and len(r.err.strip().splitlines()) == 1
