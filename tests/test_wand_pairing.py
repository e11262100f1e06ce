"""Wand frames paired by capture time (calibkit.core.pairing), against the simulator's
truth of which instant each camera frame shows (calibkit.synthetic.camclocks)."""

from __future__ import annotations

import numpy as np
import pytest

from calibkit.calibrate import wand_pipeline
from calibkit.calibrate.compare import compare_rigs
from calibkit.calibrate.wand import WandSpec
from calibkit.calibrate.wand_solve import calibrate
from calibkit.core import pairing
from calibkit.core.recording import load_observations, save_observations
from calibkit.synthetic import camclocks, sim, wand_sim

SPACING = (0.0, 0.2, 0.5)
FPS = 100.0
FRAMES = 1500
DROP_CAMERA = 2


@pytest.fixture(scope="module")
def dance():
    """A wand dance seen by 5 cameras, numbered by instant (before the cameras' clocks)."""
    rig = sim.make_rig(5, 4.0, seed=21)
    truth = sim.wand_motion(FRAMES, FPS, 4.0, SPACING, seed=21)
    obs = sim.observe(rig, truth, noise_px=0.1, ghosts_per_camera=0.2, fps=FPS, seed=21)
    return rig, obs


def _delivered(obs, drop: float, seed: int = 21, **kw):
    clocks = camclocks.make_clocks(len(obs.camera_names), seed, drift_ppm=30.0,
                                   drop={DROP_CAMERA: drop} if drop else None, **kw)
    return camclocks.per_camera(obs, clocks, FRAMES, FPS, seed), clocks


def test_pairing_learns_each_clock_and_never_mixes_instants(dance):
    _rig, obs = dance
    (raw, truth), clocks = _delivered(obs, 0.01, offset_ms=2.0, jitter_ns=200_000)
    lost = FRAMES - np.ptp(clocks.open_ns) / 1e9 * FPS
    assert np.sum(truth.camera == DROP_CAMERA) < np.sum(truth.camera == 0) + 0.005 * lost
    # the cameras' own counters pair the wrong instants (what the issue was about)
    assert camclocks.sets_mixing_instants(raw, truth, FPS)["mixing"] > 0.5 * FRAMES
    assert not pairing.frames_are_instants(raw)
    paired = pairing.pair_frames(raw)
    assert paired.method == "time"
    score = camclocks.sets_mixing_instants(paired.obs, truth, FPS)
    assert score["mixing"] == 0 and score["worst_spread_ms"] == 0.0
    # every frame a camera delivered with blobs is in a set, so the sets are the frames
    # seen by two cameras or more (counted from the truth)
    look = truth.lookup(raw.camera, raw.t_ns)
    per_trigger = np.zeros((FRAMES, len(raw.camera_names)), dtype=bool)
    per_trigger[truth.trigger[look], raw.camera] = True
    assert score["sets"] == int(np.sum(per_trigger.sum(axis=1) >= 2))
    assert sum(paired.stats["unpaired_frames"]) == 0
    # the clocks learned against the reference camera's: drift to 2 ppm, and the offset
    # between its stamps and the reference's at its first frame to 0.05 ms
    ref = raw.camera_names.index(paired.stats["reference"])
    true_rel = (1 + clocks.drift_ppm * 1e-6) / (1 + clocks.drift_ppm[ref] * 1e-6) - 1
    assert np.allclose(paired.stats["drift_ppm"], true_rel * 1e6, atol=2.0)
    first_ns = np.array([truth.trigger[truth.camera == c].min() for c in range(5)]) * 1e9 / FPS
    true_off = clocks.offset_ns - clocks.offset_ns[ref] + first_ns * true_rel
    assert np.allclose(np.array(paired.stats["offset_ms"]) * 1e6, true_off, atol=50_000)


def test_a_stamp_off_its_grid_is_left_unpaired(dance):
    _rig, obs = dance
    (raw, truth), _ = _delivered(obs, 0.0)
    # one frame of camera 1 handed over with a stamp half a period late: it cannot be
    # told which instant it shows, so it joins none
    rows = np.flatnonzero((raw.camera == 1) & (raw.frame == raw.frame[raw.camera == 1][200]))
    raw.t_ns[rows] += int(0.5e9 / FPS)
    paired = pairing.pair_frames(raw)
    assert paired.stats["unpaired_frames"][1] == 1
    kept = paired.obs
    assert not np.any((kept.camera == 1) & np.isin(kept.t_ns, raw.t_ns[rows]))
    ok = truth.lookup(kept.camera, kept.t_ns) >= 0
    assert camclocks.sets_mixing_instants(kept.select(ok), truth, FPS)["mixing"] == 0


def test_recordings_keep_each_cameras_frames_and_pair_the_same(dance, tmp_path):
    rig, obs = dance
    (raw, truth), _ = _delivered(obs, 0.01)
    expected = pairing.pair_frames(raw).obs
    for name in ("cap.mcrec", "cap.csv"):
        save_observations(tmp_path / name, raw)
        back, _ = load_observations(tmp_path / name)
        assert np.array_equal(back.frame, raw.sorted().frame)  # counters as recorded
        got = wand_pipeline.load_capture(tmp_path / name, rig)
        assert np.array_equal(got.frame, expected.frame)
        assert np.array_equal(got.t_ns, expected.t_ns)
        assert camclocks.sets_mixing_instants(got, truth, FPS)["mixing"] == 0


def test_old_recordings_numbered_by_instant_are_read_as_they_are(dance, tmp_path):
    rig, obs = dance
    save_observations(tmp_path / "old.mcrec", obs)  # no "frames" in the header
    got = wand_pipeline.load_capture(tmp_path / "old.mcrec", rig)
    assert np.array_equal(got.frame, obs.sorted().frame)
    # other tools' files often carry no times at all
    flat = obs.select(np.arange(len(obs)))
    flat.t_ns[:] = 0
    save_observations(tmp_path / "flat.csv", flat)
    assert np.array_equal(wand_pipeline.load_capture(tmp_path / "flat.csv", rig).frame,
                          obs.sorted().frame)


def test_capture_records_per_camera_and_returns_wand_frames(tmp_path):
    rig = sim.make_rig(4, 4.0, seed=5)
    run = wand_sim.setup(rig, None, "--intrinsics", None, None, 4.0, 600, SPACING, 0.1, 0.0,
                         5, with_lframe=False,
                         clocks=camclocks.make_clocks(4, 5, drop={1: 0.02}))

    class Quiet:
        def update(self, *_):
            pass

        def finish(self, *_):
            pass

    targets = wand_pipeline.CaptureTargets(10**6, 1.0)  # never enough: the whole dance
    obs, monitor = wand_pipeline.record_capture(run.batches(), WandSpec(SPACING),
                                                run.intrinsics, targets, tmp_path / "c.mcrec",
                                                wand_sim.FPS, Quiet())
    assert monitor.samples.sum() > 0
    back, _ = load_observations(tmp_path / "c.mcrec")
    assert back.meta["frames"] == pairing.PER_CAMERA
    assert len(back) == len(run.observations)
    assert camclocks.sets_mixing_instants(obs, run.frame_truth, wand_sim.FPS)["mixing"] == 0
    assert np.array_equal(wand_pipeline.load_capture(tmp_path / "c.mcrec", rig).frame,
                          obs.frame)


def test_dropped_frames_solve_as_well_as_none_dropped(dance):
    """1 % of one camera's frames lost, every clock +-30 ppm: the solve's grid RMS against
    the true rig within 10 % of the capture that lost none, and no set mixing instants."""
    rig, obs = dance
    grids = []
    for drop in (0.0, 0.01):
        (raw, truth), _ = _delivered(obs, drop)
        paired = pairing.pair_frames(raw).obs
        assert camclocks.sets_mixing_instants(paired, truth, FPS)["mixing"] == 0
        cal = calibrate(paired, rig, SPACING, holdout=0.1, seed=1)
        grids.append(compare_rigs(rig, cal.rig)["grid_rms_mm"])
    assert grids[0] < 1.0  # 0.1 px noise: well under a millimetre
    assert abs(grids[1] - grids[0]) <= 0.1 * grids[0]


def test_a_wrong_frame_rate_in_the_file_does_not_mislead_the_pairing(dance):
    _rig, obs = dance
    (raw, truth), _ = _delivered(obs, 0.01)
    raw.fps = 30.0  # the header says 30 fps; the cameras ran at 100
    assert abs(pairing.nominal_period_ns(raw) - 1e9 / FPS) < 1e5
    paired = pairing.pair_frames(raw)
    assert camclocks.sets_mixing_instants(paired.obs, truth, FPS)["mixing"] == 0
    assert sum(paired.stats["unpaired_frames"]) == 0


def test_stamps_jittering_a_fifth_of_a_period_still_pair_right():
    """Webcams stamped when the computer reads them jitter by milliseconds: 6 ms (SD) at
    30 fps, two cameras losing frames; a camera whose grid cannot be found is left out,
    none is paired with the wrong instant."""
    rig = sim.make_rig(4, 4.0, seed=1)
    truth = sim.wand_motion(1800, 30.0, 4.0, SPACING, seed=1)
    obs = sim.observe(rig, truth, noise_px=0.1, ghosts_per_camera=0.5, fps=30.0, seed=1)
    for seed in (2, 3, 4):
        clocks = camclocks.make_clocks(4, seed, offset_ms=3.0, jitter_ns=6e6, drift_ppm=100,
                                       drop={0: 0.05, 3: 0.02})
        raw, truth_f = camclocks.per_camera(obs, clocks, 1800, 30.0, seed)
        paired = pairing.pair_frames(raw)
        score = camclocks.sets_mixing_instants(paired.obs, truth_f, 30.0)
        assert score["mixing"] == 0 and score["sets"] > 1500


def test_triangulate_pairs_a_recording_whose_cameras_count_their_own_frames(dance, tmp_path,
                                                                            calibkit_cli):
    """`calibkit triangulate --from` a capture recorded per camera (each camera's own
    counter and clock, one losing 1 %): its points are the markers, as from the same blobs
    numbered by instant; read by the cameras' counters they would mix instants."""
    rig, obs = dance
    rig.save(tmp_path / "rig.toml")
    (raw, _truth), _ = _delivered(obs, 0.01)
    save_observations(tmp_path / "raw.mcrec", raw)
    save_observations(tmp_path / "instants.mcrec", obs)
    out = {}
    for name in ("raw", "instants"):
        r = calibkit_cli("triangulate", "--rig", tmp_path / "rig.toml", "--from",
                         tmp_path / f"{name}.mcrec", "--out", tmp_path / f"{name}.csv")
        assert r.code == 0, r.err
        rows = np.loadtxt(tmp_path / f"{name}.csv", delimiter=",", skiprows=1, ndmin=2,
                          usecols=range(7))
        out[name] = rows
    # three wand markers an instant in both; the per-camera one within its lost frames
    per_frame = {k: len(v) / len(np.unique(v[:, 0])) for k, v in out.items()}
    assert abs(per_frame["raw"] - per_frame["instants"]) < 0.05 * per_frame["instants"]
    # and its points are as precise (counters alone: blobs of different instants, 20x the
    # reprojection error)
    reproj = {k: np.median(v[:, 4]) for k, v in out.items()}
    assert reproj["raw"] < 1.5 * reproj["instants"]
    assert "paired by capture time" in calibkit_cli(
        "triangulate", "--rig", tmp_path / "rig.toml", "--from", tmp_path / "raw.mcrec",
        "--out", tmp_path / "again.csv").err
