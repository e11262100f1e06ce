"""`mocapd start --sim --fast` pairs the simulated cameras' frames through the multiplexer,
by their own stamps, as a live run does (daemon.synthetic.virtual), checked against the
scene's ledger of which trigger each delivered frame was."""

from __future__ import annotations

import numpy as np

from daemon.config.mocapd import Config, SimConfig
from daemon.service.daemon import Daemon
from daemon.synthetic.scene import SimScene
from daemon.synthetic.virtual import START_NS, frame_sets, spread_ns

FPS = 60.0
LOSSY = 1  # the camera that loses 1 % of its frames


def test_a_drifting_camera_that_loses_frames_never_mixes_instants():
    cfg = SimConfig(cameras=4, bodies=1, fps=FPS, seed=4, noise_px=0.0, open_spread_s=0.3,
                    clock_drift_ppm=50.0)
    scene = SimScene(cfg, n_frames=int(20 * FPS), lost_frames={LOSSY: 0.01})
    seconds = 40.0
    starts: list = []
    sets = list(frame_sets(scene, seconds, starts=starts))
    period = 1e9 / FPS
    assert abs(scene.drift_ppm[LOSSY]) > 5  # its clock does drift
    assert len(scene.lost[LOSSY]) > 0.005 * seconds * FPS
    # no set mixes instants (every sample found in the ledger)
    spreads = [spread_ns(scene, fs) for fs in sets]
    assert None not in spreads and max(spreads) <= 0.5 * period
    # once every camera delivers and its clock has settled (0.5 s later at most), every
    # trigger makes one set: complete unless the lossy camera lost that frame, and then
    # without it, never with another instant's frame in its place
    ready = max(s[0] for s in starts) + 500_000_000
    stop = START_NS + round((seconds - 0.5) * 1e9)
    window = [fs for fs in sets if ready <= fs.t_ns < stop]
    triggers = [{scene.trigger_of(s) for s in fs.samples} for fs in window]
    assert all(len(t) == 1 for t in triggers)
    triggers = np.array([t.pop() for t in triggers])
    assert np.array_equal(triggers, np.arange(triggers[0], triggers[0] + len(triggers)))
    lost = np.isin(triggers, sorted(scene.lost[LOSSY]))
    assert lost.sum() >= 0.005 * len(triggers)
    complete = np.array([len(fs.samples) == len(scene.rig) for fs in window])
    assert np.array_equal(complete, ~lost)
    without = [fs for fs, x in zip(window, lost, strict=True) if x]
    assert all(sorted(s.camera for s in fs.samples) == [0, 2, 3] for fs in without)


def test_the_fast_daemon_run_goes_through_the_multiplexer(tmp_path):
    """The daemon's own --fast loop: its figures are the multiplexer's (clocks learned from
    the cameras' stamps, samples held back while a clock settles) and no set mixes
    instants, scored from the ledger."""
    cfg = SimConfig(cameras=4, bodies=1, fps=FPS, seed=2, realtime=False,
                    clock_drift_ppm=50.0)
    daemon = Daemon(Config(sim=cfg, fps=FPS, runtime_dir=tmp_path / "rt"))
    fig = daemon.run(frames=30 * int(FPS))
    assert fig["frames"] == 30 * int(FPS)
    assert fig["multiplexer"]["settling_samples"] > 0
    assert fig["truth"]["sets_mixing_instants"] == 0
    assert fig["truth"]["sets_checked_for_instants"] == fig["frames"]
    # the drifts the multiplexer learned from the stamps: each camera's against the
    # computer's clock, within 3 ppm of the simulator's
    learned = np.array([c["clock"]["drift_ppm"] for c in fig["cameras"]])
    np.testing.assert_allclose(learned, daemon.scene.drift_ppm, atol=3.0)


def test_a_replayed_recording_of_each_cameras_own_frames_is_paired_first(tmp_path):
    """A calibkit capture (each camera's own counter and stamps, one camera losing frames)
    replayed to the daemon: its sets are instants, never counter n of every camera."""
    from calibkit.core.recording import save_observations
    from calibkit.synthetic import camclocks, sim
    from daemon.capture.sources import ReplayScene

    rig = sim.make_rig(4, 4.0, seed=3)
    truth, _ = sim.rigid_body_motion(2, 600, FPS, 4.0, seed=3)
    obs = sim.observe(rig, truth, noise_px=0.1, fps=FPS, seed=3)
    raw, frame_truth = camclocks.per_camera(
        obs, camclocks.make_clocks(4, 3, drop={LOSSY: 0.01}), 600, FPS, 3)
    save_observations(tmp_path / "cap.mcrec", raw)
    scene = ReplayScene(tmp_path / "cap.mcrec", rig)
    assert camclocks.sets_mixing_instants(scene.obs, frame_truth, FPS)["mixing"] == 0
    assert camclocks.sets_mixing_instants(raw, frame_truth, FPS)["mixing"] > 100
    assert scene.n_frames >= 600 - 0.5 * FPS  # all but the cameras' opening
