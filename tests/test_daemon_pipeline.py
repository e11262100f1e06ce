"""The multiplexer (triggered and greedy) and defining a rigid body from the live markers.
(Pairing by time on the simulator's cameras: tests/test_multiplexer.py.)"""

from __future__ import annotations

import threading
import time
from collections import deque
from dataclasses import replace

import numpy as np

from daemon.capture.pipeline import CaptureThread, Multiplexer
from daemon.capture.sources import CameraSample
from daemon.config.mocapd import load_config


def _sample(cam, index, t_ns, uv):
    uv = np.asarray(uv, float).reshape(-1, 2)
    return CameraSample(cam, index, t_ns, time.monotonic_ns(), uv, np.ones(len(uv)),
                        np.ones(len(uv)))


def test_triggered_waits_for_all_then_times_out_without_a_camera():
    mux = Multiplexer(3, "triggered", fps=100.0, timeout_frames=2.0)
    for c in range(3):
        mux.push(_sample(c, 0, 0, [[c, c]]))
    fs = mux.next(0.1)
    assert fs.index == 0 and [s.camera for s in fs.samples] == [0, 1, 2]
    mux.push(_sample(0, 1, 10_000_000, [[1, 1]]))
    mux.push(_sample(2, 1, 10_000_000, [[1, 1]]))
    t0 = time.monotonic()
    fs = mux.next(1.0)  # camera 1 never comes: emitted after two frame periods
    waited = time.monotonic() - t0
    assert fs.index == 1 and [s.camera for s in fs.samples] == [0, 2]
    assert 0.015 < waited < 0.5
    assert mux.incomplete == 1 and mux.missing.tolist() == [0, 1, 0]
    mux.push(_sample(1, 1, 10_000_000, [[1, 1]]))  # too late
    assert mux.late == 1 and mux.next(0.02) is None


def test_a_cameras_rate_is_its_recent_frames_over_their_span_and_0_once_it_stops():
    """The status's per-camera rate (the live test reads only that frames keep coming):
    the frame times kept, over the time they span; 0 when the last is over a second old."""
    cap = CaptureThread.__new__(CaptureThread)  # its times alone: no source, no thread
    cap.times = deque(maxlen=256)
    assert cap.rate_hz() == 0.0
    now = time.monotonic_ns()
    cap.times.extend(now - int(k * 1e9 / 120) for k in range(200, -1, -1))
    assert abs(cap.rate_hz() - 120.0) < 1e-6
    cap.times = deque(t - 2_000_000_000 for t in cap.times)  # the camera stopped 2 s ago
    assert cap.rate_hz() == 0.0


def test_triggered_does_not_wait_for_a_disconnected_camera():
    connected = np.array([True, False, True])
    mux = Multiplexer(3, "triggered", fps=100.0, connected=lambda: connected)
    mux.push(_sample(0, 5, 0, [[0, 0]]))
    mux.push(_sample(2, 9, 0, [[0, 0]]))  # counters differ: paired by time
    fs = mux.next(0.0)
    assert fs.index == 0 and [s.camera for s in fs.samples] == [0, 2]


def test_greedy_extrapolates_other_cameras_to_the_newest_time():
    """Blobs move at (200, -100) px/s; camera 1 reports 3 ms after camera 0: camera 0's
    blob must be moved to where it is at camera 1's time."""
    v = np.array([200.0, -100.0])
    mux = Multiplexer(2, "greedy")
    starts = np.array([[100.0, 200.0], [300.0, 50.0]])
    for k in range(3):
        t0 = k * 10_000_000
        mux.push(_sample(0, k, t0, starts + v * t0 * 1e-9))
        t1 = t0 + 3_000_000
        mux.push(_sample(1, k, t1, [[10.0, 10.0]]))
    sets = []
    while (fs := mux.next(0.0)) is not None:
        sets.append(fs)
    last = sets[-1]
    assert last.t_ns == 23_000_000
    cam0 = [s for s in last.samples if s.camera == 0][0]
    np.testing.assert_allclose(cam0.uv, starts + v * 23e-3, atol=1e-9)


def test_blob_velocity_halves_the_noise_with_three_samples_and_skips_unmatched_blobs():
    """Two blobs at constant velocity with 0.2 px noise: the velocity from three samples
    scatters about half as much as from two; a blob appearing from nowhere gets none."""
    from daemon.capture.pipeline import blob_velocity

    rng = np.random.default_rng(0)
    v = np.array([[300.0, -150.0], [-80.0, 40.0]]) * 1e-9  # px per ns
    start = np.array([[100.0, 100.0], [400.0, 300.0]])
    dt = 10_000_000
    two, three = [], []
    for _ in range(300):
        hist = [_sample(0, k, k * dt, start + v * k * dt + rng.normal(0, 0.2, (2, 2)))
                for k in range(3)]
        two.append(blob_velocity(hist[1:]) - v)
        three.append(blob_velocity(hist) - v)
    ratio = np.std(np.array(three)) / np.std(np.array(two))
    assert 0.4 < ratio < 0.6  # sqrt(2 * 0.2^2) / 2 over sqrt(2 * 0.2^2): 0.5
    new = _sample(0, 3, 3 * dt, np.vstack([start + v * 3 * dt, [[50.0, 50.0]]]))
    vel = blob_velocity([hist[-1], new])
    np.testing.assert_allclose(vel[2], 0.0)
    np.testing.assert_allclose(vel[:2], v, atol=0.2 * 3 / dt)


def test_updates_closer_than_a_frame_move_the_velocity_less():
    """A still marker seen every 1 ms (a set per camera report) with 0.3 px noise: weighed
    by the frame period, its velocity stays near zero; weighed as whole frames it is thrown
    around by noise / 1 ms."""
    from calibkit.synthetic import sim
    from daemon.tracking.tracker import Tracker

    rig = sim.make_rig(6, 4.0, seed=3)
    truth = sim.static_markers(1, 200, 4.0, seed=1)
    obs = sim.observe(rig, truth, noise_px=0.3, fps=1000.0, seed=2)
    speeds = {}
    for period in (None, 1 / 60):
        tr = Tracker(rig)
        tr.period_s = period
        vel = []
        for f in range(200):
            m = obs.frame == f
            tr.update(obs.camera[m], obs.uv[m], f * 1_000_000)
            if f > 20:
                vel.append(np.linalg.norm(tr.vel, axis=1))
        speeds[period] = float(np.sqrt(np.mean(np.square(np.concatenate(vel)))))
    assert speeds[1 / 60] < 0.25 * speeds[None]


def test_rigid_body_from_live_markers(tmp_path, mocapd_cli):
    """A daemon sees one unknown body; `rigid-body add --from-live` defines it, the daemon
    reloads and tracks it."""
    from daemon.service.daemon import Daemon

    cfg_path = tmp_path / "mocapd.toml"
    cfg_path.write_text("# my rig\n[sim]\ncameras = 6\nbodies = 1\nfps = 100.0\n"
                        "define_bodies = false\nseed = 4\n")
    rt = tmp_path / "rt"
    cfg = replace(load_config(cfg_path), runtime_dir=rt)
    daemon = Daemon(cfg, extend=lambda c: replace(c, runtime_dir=rt))
    thread = threading.Thread(target=daemon.run, kwargs={"duration_s": 8.0}, daemon=True)
    thread.start()
    try:
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:
            if (rt / "mocapd.sock").exists() and getattr(daemon, "pipeline", None) and \
                    daemon.pipeline.stats.frames > 20:
                break
            time.sleep(0.05)
        assert daemon.pipeline.rigid.bodies == []
        r = mocapd_cli("rigid-body", "add", "probe", "--config", cfg_path, "--from-live",
                       "--runtime-dir", rt)
        assert r.code == 0, r.err
        text = cfg_path.read_text()
        assert text.startswith("# my rig") and "[[rigid_body]]" in text  # comments kept
        (body,) = load_config(cfg_path).bodies
        assert body.name == "probe" and body.id == 1 and len(body.markers) == 4
        np.testing.assert_allclose(body.markers.mean(axis=0), 0, atol=1e-6)
        truth = daemon.scene.bodies_truth[0].markers_body
        d_true = np.sort(np.linalg.norm(truth[:, None] - truth[None], axis=2).ravel())
        d_new = np.sort(np.linalg.norm(body.markers[:, None] - body.markers[None],
                                       axis=2).ravel())
        np.testing.assert_allclose(d_new, d_true, atol=0.003)
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline and not (
                daemon.pipeline.last_result is not None
                and daemon.pipeline.last_result.poses.valid.tolist() == [True]):
            # status is asked while the reload swaps the bodies: it never fails
            bodies = daemon.status()["bodies"]
            assert [b["name"] for b in bodies] in ([], ["probe"])
            time.sleep(0.01)
        assert daemon.pipeline.last_result.poses.valid.tolist() == [True]
        assert daemon.status()["bodies"] == [{"id": 1, "name": "probe", "valid": True}]
        r = mocapd_cli("rigid-body", "list", "--config", cfg_path)
        assert r.code == 0 and "probe" in r.out
        r = mocapd_cli("rigid-body", "add", "probe", "--config", cfg_path, "--from-live",
                       "--runtime-dir", rt)
        assert r.code == 2 and "exists already" in r.err
    finally:
        mocapd_cli("stop", "--runtime-dir", rt)
        thread.join(10)
    assert not thread.is_alive()


def test_idle_hooks_run_off_the_frame_path_in_order_and_never_pile_up(monkeypatch):
    """The scorers' hooks (idle_hooks) see every result, oldest first, but only when the
    frame loop has time (run_idle), never inside process(); a loop that never idles runs
    them once their queue is full, so it stays bounded."""
    from calibkit.synthetic import sim
    from daemon.capture import pipeline as pl
    from daemon.capture.multiplexer import FrameSet
    from daemon.tracking.rigid import RigidConfig
    from daemon.tracking.tracker import TrackerConfig

    rig = sim.make_rig(3, 4.0, seed=1)
    seen, during = [], []
    pipe = pl.Pipeline(rig, TrackerConfig(), RigidConfig(), [],
                       hooks=[lambda r: during.append(len(seen))],
                       idle_hooks=[lambda r: seen.append(r.frame)])
    empty = [CameraSample(c, 0, 0, 0, np.zeros((0, 2)), np.zeros(0), np.zeros(0))
             for c in range(3)]
    for i in range(5):
        pipe.process(FrameSet(i, i * 10**7, i * 10**7, empty))
    assert seen == [] and during == [0] * 5 and pipe.idle_pending == 5
    pipe.run_idle(2)
    assert seen == [0, 1] and pipe.idle_pending == 3
    pipe.run_idle()
    assert seen == [0, 1, 2, 3, 4] and pipe.idle_pending == 0
    monkeypatch.setattr(pl, "IDLE_BACKLOG", 3)
    for i in range(5, 12):
        pipe.process(FrameSet(i, i * 10**7, i * 10**7, empty))
    assert pipe.idle_pending == 3 and seen == list(range(9))
