"""The simulator's scorer (daemon.synthetic.evaluator.Evaluator): pose errors, gross errors,
identity swaps and sets that mix instants it must count, from hand-made frames whose answers
are known. The truth reaches it only through the scene's ledger, by each sample's camera,
frame id and timestamp."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from daemon.capture.pipeline import FrameResult
from daemon.config.mocapd import SimConfig
from daemon.synthetic.evaluator import Evaluator
from daemon.synthetic.scene import SimScene
from daemon.tracking.rigid import BodyPoses
from daemon.tracking.tracker import TrackFrame

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


def test_defined_bodies_are_matched_to_the_scenes_by_shape():
    """Bodies defined live carry their own frames, marker order and ids: the scorer finds
    which is which from their shapes alone and scores each pose in the scene body's frame,
    so a pose that is right for the defined body scores (near) zero, and a decoy shape is
    matched to nothing."""
    from daemon.tracking.rigid import BodyDef

    scene = _scene()
    rng = np.random.default_rng(3)
    true_a, true_b = (b.markers_body for b in scene.bodies_truth)
    R_off = Rotation.from_rotvec([0.3, -0.5, 1.1]).as_matrix()
    t_off = np.array([0.01, -0.02, 0.005])
    perm_a, perm_b = np.array([2, 0, 1]), np.array([1, 2, 0])
    # defined = R_off @ true + t_off, markers listed in another order, 0.1 mm of noise
    def_a = np.empty_like(true_a)
    def_a[perm_a] = true_a @ R_off.T + t_off + rng.normal(0, 1e-4, true_a.shape)
    def_b = np.empty_like(true_b)
    def_b[perm_b] = true_b + rng.normal(0, 1e-4, true_b.shape)
    decoy = np.array([[0.0, 0.0, 0.0], [0.2, 0.0, 0.0], [0.0, 0.15, 0.0]])
    defs = [BodyDef("decoy", 3, decoy, np.zeros(3)), BodyDef("b", 7, def_b, np.zeros(3)),
            BodyDef("a", 9, def_a, np.zeros(3))]
    ev = Evaluator(scene, skip_frames=0, bodies=defs)
    assert ev.ids.tolist() == [9, 7]
    # the slot check follows the defined marker order
    assert ev.marker_ids[0][perm_a].tolist() == scene.bodies_truth[0].marker_ids.tolist()
    assert ev.marker_ids[1][perm_b].tolist() == scene.bodies_truth[1].marker_ids.tolist()
    # poses right for the defined frames: a's frame is R_off^T-turned and offset
    where = [b.poses[0, :3, 3] for b in scene.bodies_truth]
    R = np.stack([np.eye(3), np.eye(3), R_off.T])
    pos = np.array([[0.5, 0.5, 0.5], where[1], where[0] - R_off.T @ t_off])
    t = PERIOD
    samples = [scene.deliver(c, 1, 1, 10**9 + PERIOD, t, t, t) for c in range(2)]
    uv = np.concatenate([s.uv for s in samples])
    tracks = TrackFrame(np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros(0, bool),
                        np.zeros(0, np.int64), np.zeros((0, 1), np.int64),
                        np.zeros(0, np.int64))
    poses = BodyPoses(np.array([3, 7, 9]), np.ones(3, bool), pos, R, np.zeros((3, 4)),
                      np.zeros(3), np.full(3, 3), np.full((3, 3), -1))
    ev(FrameResult(1, t, t, t, np.zeros(len(uv), np.int64), uv, tracks, poses, samples))
    fig = ev.figures()
    assert fig["valid_poses"] == 2 and fig["gross_error_frames"] == 0
    assert fig["bodies"]["body0"]["defined_as"] == "a"
    assert fig["bodies"]["body0"]["definition_error_mm_rms"] < 0.3
    # the definitions' 0.1 mm noise is all that is left
    assert fig["position_error_mm_rms"] < 0.5 and fig["orientation_error_deg_rms"] < 0.5
    # the same poses scored as if the defined frames were the scene's are far off
    naive = Evaluator(scene, skip_frames=0)
    naive.ids[:] = [9, 7]
    naive(FrameResult(1, t, t, t, np.zeros(len(uv), np.int64), uv, tracks, poses, samples))
    assert naive.figures()["orientation_error_deg_rms"] > 20
