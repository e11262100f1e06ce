"""The simulator's scorer (daemon.synthetic.evaluator.Evaluator): pose errors, gross errors,
identity swaps and sets that mix instants it must count, from hand-made frames whose answers
are known. The truth reaches it only through the scene's ledger, by each sample's camera,
frame id and timestamp."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from daemon.config import SimConfig
from daemon.pipeline import FrameResult
from daemon.rigid import BodyPoses
from daemon.synthetic.evaluator import Evaluator
from daemon.synthetic.scene import SimScene
from daemon.tracker import TrackFrame

FPS = 100.0
PERIOD = round(1e9 / FPS)


def _scene():
    """A real scene (two bodies of three markers, three cameras) whose bodies are then
    held still at known poses, so every error below is the one the frame was given."""
    scene = SimScene(SimConfig(cameras=3, bodies=2, markers_per_body=3, fps=FPS, seed=1,
                               noise_px=0.0), n_frames=20)
    for b, where in zip(scene.bodies_truth, ([0.0, 0.0, 1.0], [1.0, 0.0, 0.5]), strict=True):
        b.poses[:] = np.eye(4)
        b.poses[:, :3, 3] = where
    return scene


def _result(scene, f, marker_of_track, offset_a, rot_b_deg, late_camera_ns=0):
    """Six tracks (ids 10..15) over the blobs cameras 0 and 1 delivered at trigger f (the
    second camera's frame taken late_camera_ns late); track k holds a blob of the true
    marker marker_of_track[k]. Body a (id 1) holds tracks 10-12, b tracks 13-15."""
    t = f * PERIOD
    samples = [scene.deliver(c, f, f, 10**9 + f * PERIOD, t + late, t + late, t + late)
               for c, late in ((0, 0), (1, late_camera_ns))]
    markers = np.concatenate([scene.markers(s) for s in samples])
    blob_of = [int(np.flatnonzero(markers == m)[0]) for m in marker_of_track]
    ids = np.arange(10, 16)
    tracks = TrackFrame(ids, np.zeros((6, 3)), np.ones(6, bool), np.full(6, 2),
                        np.array(blob_of)[:, None], np.zeros(6, np.int64))
    rot_b = Rotation.from_rotvec([0, 0, np.radians(rot_b_deg)]).as_matrix()
    R = np.stack([np.eye(3), rot_b])
    pos = np.array([np.add([0.0, 0.0, 1.0], offset_a), [1.0, 0.0, 0.5]])
    poses = BodyPoses(np.array([1, 2]), np.array([True, True]), pos, R,
                      np.zeros((2, 4)), np.zeros(2), np.array([3, 3]),
                      np.array([[10, 11, 12], [13, 14, 15]]))
    uv = np.concatenate([s.uv for s in samples])
    return FrameResult(f, t, t, t, np.zeros(len(uv), np.int64), uv, tracks, poses, samples)


def test_errors_gross_frames_swaps_and_mixed_sets_are_counted():
    scene = _scene()
    ev = Evaluator(scene, skip_frames=1)
    a_ids = [int(m) for m in scene.bodies_truth[0].marker_ids]
    b_ids = [int(m) for m in scene.bodies_truth[1].marker_ids]
    right = a_ids + b_ids
    swapped = [b_ids[0]] + a_ids[1:] + [a_ids[0]] + b_ids[1:]  # tracks 10 and 13 swap
    ev(_result(scene, 0, right, [0, 0, 0], 0))  # skipped (its set is still checked)
    ev(_result(scene, 1, right, [0.001, 0, 0], 0.1))
    ev(_result(scene, 2, right, [0, 0.003, 0], 0.3, late_camera_ns=PERIOD // 3))
    ev(_result(scene, 3, swapped, [0, 0, 0], 0, late_camera_ns=PERIOD))  # a frame apart
    ev(_result(scene, 4, swapped, [0, 0, 0], 6.0))  # still swapped; b 6 degrees off
    fig = ev.figures()
    assert fig["track_swaps"] == 2  # counted once, when the identity changed
    assert fig["body_swaps"] == 2  # both bodies took a marker of the other, once each
    assert fig["gross_error_frames"] == 1 and fig["bodies"]["body1"]["gross_error_frames"] == 1
    a, b = fig["bodies"]["body0"], fig["bodies"]["body1"]
    assert a["valid_fraction"] == 1.0 and fig["frames_scored"] == 4
    # the RMS counts every valid pose, the gross one included; without it, named so
    np.testing.assert_allclose(a["position_error_mm_rms"], np.sqrt((1 + 9) / 4), rtol=1e-9)
    np.testing.assert_allclose(b["orientation_error_deg_rms"],
                               np.sqrt((0.1**2 + 0.3**2 + 6.0**2) / 4), rtol=1e-6)
    np.testing.assert_allclose(b["orientation_error_deg_rms_without_gross"],
                               np.sqrt((0.1**2 + 0.3**2) / 3), rtol=1e-6)
    np.testing.assert_allclose(b["orientation_error_deg_max"], 6.0, rtol=1e-6)
    assert fig["valid_poses"] == 8
    # a third of a frame apart is one instant; a whole frame apart is two
    assert fig["sets_checked_for_instants"] == 5 and fig["sets_mixing_instants"] == 1
    np.testing.assert_allclose(fig["set_instant_spread_ms_max"], 10.0)
    assert fig["samples_not_in_ledger"] == 0


def test_samples_the_scene_never_delivered_are_not_scored_as_truth():
    scene = _scene()
    ev = Evaluator(scene, skip_frames=0)
    ids = [int(m) for b in scene.bodies_truth for m in b.marker_ids]
    r = _result(scene, 1, ids, [0, 0, 0], 0)
    r.samples[1].device_time_ns += 1  # not what the camera stamped
    ev(r)
    fig = ev.figures()
    assert fig["samples_not_in_ledger"] == 1 and fig["sets_checked_for_instants"] == 0
    assert fig["track_swaps"] == 0 and fig["valid_poses"] == 2
