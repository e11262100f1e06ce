"""The simulator's scorer (daemon.synthetic.evaluator.Evaluator): pose errors and identity swaps it
must count, from hand-made frames whose answers are known."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
from scipy.spatial.transform import Rotation

from daemon.pipeline import FrameResult
from daemon.rigid import BodyPoses
from daemon.synthetic.evaluator import Evaluator
from daemon.tracker import TrackFrame


def _scene(n_frames):
    poses = np.tile(np.eye(4), (2, n_frames, 1, 1))
    poses[1, :, :3, 3] = [1.0, 0.0, 0.5]
    bodies = [SimpleNamespace(id=1, name="a", marker_ids=np.array([0, 1, 2]), poses=poses[0]),
              SimpleNamespace(id=2, name="b", marker_ids=np.array([3, 4, 5]), poses=poses[1])]
    return SimpleNamespace(bodies_truth=bodies)


def _result(f, marker_of_track, offset_a, rot_b_deg):
    """Six tracks (ids 10..15), one blob each in one camera; body a holds tracks 10-12."""
    ids = np.arange(10, 16)
    tracks = TrackFrame(ids, np.zeros((6, 3)), np.ones(6, bool), np.full(6, 2),
                        np.arange(6)[:, None], np.zeros(6, np.int64))
    rot_b = Rotation.from_rotvec([0, 0, np.radians(rot_b_deg)]).as_matrix()
    R = np.stack([np.eye(3), rot_b])
    pos = np.array([offset_a, [1.0, 0.0, 0.5]])
    poses = BodyPoses(np.array([1, 2]), np.array([True, True]), pos, R,
                      np.zeros((2, 4)), np.zeros(2), np.array([3, 3]),
                      np.array([[10, 11, 12], [13, 14, 15]]))
    return FrameResult(f, f, f, f, np.zeros(6, np.int64), np.zeros((6, 2)), tracks, poses,
                       blob_marker=np.asarray(marker_of_track), scene_frame=f)


def test_errors_gross_frames_and_swaps_are_counted():
    ev = Evaluator(_scene(6), skip_frames=1)
    right = [0, 1, 2, 3, 4, 5]
    ev(_result(0, right, [0, 0, 0], 0))  # skipped
    ev(_result(1, right, [0.001, 0, 0], 0.1))
    ev(_result(2, right, [0, 0.003, 0], 0.3))
    ev(_result(3, [3, 1, 2, 0, 4, 5], [0, 0, 0], 0))  # tracks 10 and 13 swap markers
    ev(_result(4, [3, 1, 2, 0, 4, 5], [0, 0, 0], 6.0))  # still swapped; b 6 degrees off
    fig = ev.figures()
    assert fig["track_swaps"] == 2  # counted once, when the identity changed
    assert fig["body_swaps"] == 2  # both bodies took a marker of the other, once each
    assert fig["gross_error_frames"] == 1 and fig["bodies"]["b"]["gross_error_frames"] == 1
    a, b = fig["bodies"]["a"], fig["bodies"]["b"]
    assert a["valid_fraction"] == 1.0 and fig["frames_scored"] == 4
    np.testing.assert_allclose(a["position_error_mm_rms"], np.sqrt((1 + 9) / 4), rtol=1e-9)
    np.testing.assert_allclose(b["orientation_error_deg_rms"],
                               np.sqrt((0.1**2 + 0.3**2) / 3), rtol=1e-6)
    np.testing.assert_allclose(b["orientation_error_deg_max"], 0.3, rtol=1e-6)
