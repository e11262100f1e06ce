"""Frames paired by capture time (daemon.capture.multiplexer, daemon.capture.clocks), on the
simulator's cameras run in virtual time (daemon.synthetic.virtual): cameras that open up to 2 s
apart, a camera that reconnects with a new counter and clock epoch, clocks drifting by 50 ppm for
two minutes. Every set is checked against the simulator's truth: the instants its cameras
really took their frames (the scene's ledger, found from each sample's own frame id and
timestamp). benchmarks/bench_pairing.py runs the same scenes with pairing by counter."""

from __future__ import annotations

import numpy as np

from daemon.capture.clocks import SETTLE_NS, CameraClock
from daemon.config.mocapd import SimConfig
from daemon.synthetic import virtual
from daemon.synthetic.scene import SimScene
from daemon.synthetic.virtual import START_NS, capture


def spread_ns(scene, fs) -> int:
    """How far apart the set's cameras really took their frames (the ledger's truth)."""
    spread = virtual.spread_ns(scene, fs)
    assert spread is not None  # every sample found by its camera's frame id and timestamp
    return spread


def _scene(**kw) -> SimScene:
    cfg = SimConfig(**{**dict(cameras=4, bodies=1, fps=60.0, seed=3, noise_px=0.0,
                              open_spread_s=0.0, clock_drift_ppm=0.0), **kw})
    return SimScene(cfg, n_frames=int(20 * cfg.fps))


def test_cameras_opening_up_to_two_seconds_apart_pair_by_instant():
    scene = _scene(open_spread_s=2.0)
    assert scene.open_delay_ns.max() == 2e9  # the last camera opens 2 s after the first
    sets, mux, starts = capture(scene, 4.0)
    half = 0.5e9 / scene.fps
    assert max(spread_ns(scene, fs) for fs in sets) <= half  # none mixes instants
    # once every camera is open, every set is whole: no sample is late or left out
    all_open = max(s[0] for s in starts)
    after = [fs for fs in sets if fs.t_ns > all_open + 1e8]
    assert len(after) > 0.95 * (START_NS + 4e9 - all_open - 1e8) * scene.fps * 1e-9
    assert all(len(fs.samples) == 4 for fs in after)
    # frame numbers count frame periods: consecutive sets one apart
    assert np.all(np.diff([fs.index for fs in after]) == 1)
    # the counters do not agree across cameras: the first camera's is ahead by its head start
    last = after[-1].samples
    ids = np.array([s.device_frame_id for s in last])
    assert ids.max() - ids.min() > 1.5 * scene.fps


def test_a_reconnecting_camera_pairs_again_at_once():
    """cam1 disconnects for 0.5 s and comes back counting from 0 on a new clock epoch:
    once its clock has settled again (a tenth of a second), its frames are in the sets of
    their own instant."""
    scene = _scene(drop_camera="cam1", drop_from_s=1.0, drop_for_s=0.5, clock_drift_ppm=50.0)
    sets, mux, starts = capture(scene, 3.0)
    half = 0.5e9 / scene.fps
    assert max(spread_ns(scene, fs) for fs in sets) <= half
    assert len(starts[1]) == 2  # opened, then reopened once the drop was over
    back = starts[1][1]
    assert back - (START_NS + 1.5e9) < 0.25e9  # the first reopen after the drop
    with_cam1 = [fs for fs in sets if any(s.camera == 1 for s in fs.samples)]
    first_back = min(fs.t_ns for fs in with_cam1 if fs.t_ns > START_NS + 1.2e9)
    assert first_back - back <= SETTLE_NS + 2e9 / scene.fps
    after = [fs for fs in sets if fs.t_ns > back + 1e8]
    assert all(len(fs.samples) == 4 for fs in after)
    assert mux.late <= 2
    assert mux.clocks[1].resets == 1


def test_a_camera_whose_thread_stalls_as_it_opens_never_mixes_instants():
    """The late opener's capture thread does not run for its first 0.12-0.4 s (a busy
    computer): the frames it took meanwhile arrive together, late. None of them may set
    its clock: a clock that settled on such frames put them, and the next ones, a frame
    or more off (one set in 340 mixed instants here before the clock waited for frames
    on time). Once the stall is over, its frames join their sets within the settling."""
    for stall_ns in (120_000_000, 250_000_000, 400_000_000):
        cfg = SimConfig(cameras=5, bodies=1, fps=100.0, seed=11, noise_px=0.0,
                        open_spread_s=1.5, clock_drift_ppm=50.0)
        scene = SimScene(cfg, n_frames=int(10 * cfg.fps))
        late = int(np.argmax(scene.open_delay_ns))
        opens = int(scene.open_delay_ns[late])
        sets, mux, starts = capture(scene, 3.0,
                                    stalls={late: [(opens - 10**6, opens + stall_ns)]})
        half = 0.5e9 / scene.fps
        assert max(spread_ns(scene, fs) for fs in sets) <= half, stall_ns
        back = START_NS + opens + stall_ns
        joined = min(fs.t_ns for fs in sets if any(s.camera == late for s in fs.samples))
        assert joined - back <= SETTLE_NS + 3e9 / scene.fps


def test_clocks_drifting_50_ppm_for_two_minutes_stay_paired():
    """Three cameras at 120 fps whose clocks gain or lose up to 50 ppm: over two minutes
    they drift apart by up to 11 ms, more than a frame. An offset alone (no drift) lets a
    losing clock fall more than half a frame behind within 90 s; the learned drift keeps
    every set to one instant, and follows each camera's true drift."""
    scene = _scene(cameras=3, fps=120.0, clock_drift_ppm=50.0, seed=6)
    assert scene.drift_ppm.min() < -45 and scene.drift_ppm.max() > 40
    sets, mux, _ = capture(scene, 120.0)
    half = 0.5e9 / scene.fps
    assert len(sets) > 0.99 * 120 * scene.fps
    assert max(spread_ns(scene, fs) for fs in sets) <= half
    assert sum(len(fs.samples) < 3 for fs in sets) <= 2  # the first set or two
    learned = np.array([c.drift_ppm for c in mux.clocks])
    np.testing.assert_allclose(learned, scene.drift_ppm, atol=1.0)


def test_clock_model_ignores_stalls_restarts_when_time_goes_back_and_follows_a_jump():
    """The envelope of arrival - device time: late frames (a busy computer, up to 150 ms)
    do not move it; a device time that goes back restarts the clock; frames suddenly
    arriving earlier than the envelope allows (the camera's time jumped 30 ms forward)
    lower it at once, the drift kept."""
    rng = np.random.default_rng(1)
    period = 1e9 / 120
    clock = CameraClock(period)
    n = 120 * 30
    taken = 5e9 + np.arange(n) * period
    device = (7e11 + (taken - taken[0]) * (1 - 40e-6)).round().astype(np.int64)
    delay = 4e5 + rng.exponential(5e4, n)
    stalled = rng.random(n) < 0.01
    delay[stalled] += rng.uniform(1e6, 150e6, stalled.sum())
    est = np.array([clock.capture_ns(int(d), int(t + e))
                    for d, t, e in zip(device, taken, delay, strict=True)])
    err = est - taken
    assert clock.resets == 0 and clock.lowered == 0
    assert np.all(np.abs(err[n // 10:] - 4e5) < 0.2 * period)  # the smallest delay, 0.4 ms
    np.testing.assert_allclose(clock.drift_ppm, -40.0, atol=1.0)  # it loses 40 ppm
    # the camera's time jumps 30 ms forward: the next frame is mapped where it belongs
    t = taken[-1] + period
    d = int(device[-1]) + round(period * (1 - 40e-6)) + 30_000_000
    assert abs(clock.capture_ns(d, int(t + 4e5)) - (t + 4e5)) < 1e4
    assert clock.lowered == 1 and clock.resets == 0
    np.testing.assert_allclose(clock.drift_ppm, -40.0, atol=1.0)
    # it restarts its clock: device time back near zero; mapped from its arrival
    t += period
    assert abs(clock.capture_ns(1000, int(t + 4e5)) - (t + 4e5)) < 1
    assert clock.resets == 1 and not clock.settled
