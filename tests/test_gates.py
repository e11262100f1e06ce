"""Gates that follow the rig's residual: the rule, the rig file's figure, the estimate from
data, and what triangulation and the daemon's tracker make of them."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.stats import chi2, norm

from calibkit.core.camera import Rig
from calibkit.core.errors import UserError
from calibkit.core.observations import Truth
from calibkit.core.recording import save_observations
from calibkit.synthetic import sim
from calibkit.synthetic.miscalibrate import labelled_residual_px, miscalibrated
from calibkit.synthetic.truthcheck import score_points
from calibkit.vision.correspondence import CorrespondenceConfig, match_frames
from calibkit.vision.gates import (
    K_EPIPOLAR,
    K_REPROJ,
    correspondence_config,
    estimate_residual,
    gated_config,
    point_residuals,
    rig_residual,
    rig_residual_px,
)

NOISE_PX = 0.3  # centroid noise; the rest of the 1 px residual is the calibration's error


def _take(rig: Rig, n_frames: int, seed: int):
    """50 markers at random in every frame, 20 % hidden per camera, 2 stray blobs per camera
    per frame, rendered with the true rig."""
    rng = np.random.default_rng(seed)
    lo, hi = sim.volume_box(4.0)
    xyz = rng.uniform(lo + 0.1 * (hi - lo), hi - 0.1 * (hi - lo), (n_frames, 50, 3))
    truth = Truth(np.repeat(np.arange(n_frames), 50), np.tile(np.arange(50), n_frames),
                  xyz.reshape(-1, 3))
    obs = sim.observe(rig, truth, noise_px=NOISE_PX, dropout=0.2, ghosts_per_camera=2.0,
                      seed=seed + 1)
    return truth, obs


@pytest.fixture(scope="module")
def webcams():
    """Four cameras (the user's webcam rig) and a calibration of them that leaves 1 px."""
    true = sim.make_rig(4, 4.0, seed=11)
    est, recorded = miscalibrated(true, 1.0, NOISE_PX, seed=3)
    truth, obs = _take(true, 30, seed=5)
    return true, est, recorded, truth, obs


def test_the_constants_are_the_quantiles_they_claim() -> None:
    # a 2D error: |e|^2 / s^2 is chi-square(2), s = residual / sqrt(2)
    assert K_REPROJ == pytest.approx(np.sqrt(chi2.ppf(0.999, 2) / 2), rel=1e-9)
    # a 1D epipolar distance carrying both blobs' errors, gain up to 2: s sqrt(5)
    assert K_EPIPOLAR == pytest.approx(norm.ppf(1 - 0.0005) * np.sqrt(5 / 2), rel=1e-9)


def test_gates_scale_with_the_residual_and_never_shrink_below_the_defaults() -> None:
    d = CorrespondenceConfig()
    for r in (None, 0.0, 0.1, float("nan")):
        cfg = correspondence_config(r)
        assert (cfg.epipolar_px, cfg.max_reproj_px) == (d.epipolar_px, d.max_reproj_px)
    cfg = correspondence_config(1.0)
    assert cfg.epipolar_px == pytest.approx(K_EPIPOLAR)
    assert cfg.max_reproj_px == pytest.approx(K_REPROJ)
    kept = correspondence_config(1.0, CorrespondenceConfig(epipolar_px=3.0), {"epipolar_px"})
    assert kept.epipolar_px == 3.0 and kept.max_reproj_px == pytest.approx(K_REPROJ)


def test_the_reprojection_gate_keeps_all_but_a_tenth_of_a_percent(webcams) -> None:
    """The rule's premise, on a miscalibrated rig: true blobs' errors after triangulation,
    in units of the residual, have the chi-square tail the gate is set from."""
    _, est, recorded, truth, obs = webcams
    rows, xyz = _true_points(est, obs)
    error = point_residuals(est, obs, rows, xyz)
    r = np.sqrt(np.mean(error**2))
    assert r == pytest.approx(recorded, rel=0.15)  # the take has the calibration's residual
    beyond = np.mean(error > K_REPROJ * r)
    assert beyond < 0.004  # 0.1 % for a 2D normal error; a rig's error is not quite one


def _true_points(rig, obs):
    """Every marker seen by >= 3 cameras, triangulated from its true blobs: (rows, xyz)."""
    from calibkit.core.geometry import triangulate

    real = np.flatnonzero(obs.marker >= 0)
    key = obs.frame[real] * 1000 + obs.marker[real]
    _, point, counts = np.unique(key, return_inverse=True, return_counts=True)
    keep = counts[point] >= 3
    rows = real[keep]
    _, point = np.unique(point[keep], return_inverse=True)
    cam = obs.camera[rows].astype(np.int64)
    tri = triangulate(rig, point, cam, obs.uv[rows])
    table = np.full((len(tri.xyz), len(rig)), -1, dtype=np.int64)
    table[point, cam] = rows
    return table, tri.xyz


def test_a_rig_leaving_1px_triangulates_95_percent_at_the_defaults(webcams) -> None:
    """The rig file records its 1 px: the default gates follow it and recover >= 95 % of
    the markers >= 3 cameras saw, <= 0.5 % ghosts; the old fixed gates lose > 5 %."""
    _, est, recorded, truth, obs = webcams
    rig = Rig(est.cameras, {"reprojection_rms_px": recorded}, dict(est.meta))
    cfg, residual = gated_config(rig, obs)
    assert residual.source == "rig file" and residual.px == recorded
    points = match_frames(rig, obs, cfg)
    score = score_points(points.frame, points.xyz, truth, obs, rows=points.rows)
    assert score.recall_3 >= 0.95 and score.ghost_fraction <= 0.005
    old = match_frames(rig, obs, CorrespondenceConfig())
    old_score = score_points(old.frame, old.xyz, truth, obs, rows=old.rows)
    assert old_score.recall_3 < 0.93
    # the error is counted over every point, and the gross ones beside it
    assert score.matched + score.ghosts == score.points
    assert 0 < score.gross_errors < score.matched


def test_a_rig_file_without_a_residual_gets_one_measured_on_the_data(webcams) -> None:
    _, est, _, truth, obs = webcams
    rig = Rig(est.cameras, {}, dict(est.meta))
    assert rig_residual(rig) is None
    truth_px = labelled_residual_px(est, obs)
    found = estimate_residual(rig, obs)
    assert found.source == "estimated from data"
    assert found.px == pytest.approx(truth_px, rel=0.3)
    cfg, residual = gated_config(rig, obs)
    assert residual.source == "estimated from data"
    points = match_frames(rig, obs, cfg)
    score = score_points(points.frame, points.xyz, truth, obs, rows=points.rows)
    assert score.recall_3 >= 0.95 and score.ghost_fraction <= 0.005


def test_a_residual_with_a_tail_is_measured_not_censored_by_its_own_gates() -> None:
    """Real cameras' residual has a tail (docs/triangulation.md, Real webcams); here 5 % of
    the blobs are pulled 1.5-3 px aside. Measured through the reprojection gate it sets, the
    estimate cut that tail off and read about a third low; through one twice as wide it
    reads what the true labels give."""
    true = sim.make_rig(4, 4.0, seed=1)
    _, obs = _take(true, 60, seed=7)
    rng = np.random.default_rng(8)
    pulled = rng.random(len(obs)) < 0.05
    angle = rng.uniform(0.0, 2.0 * np.pi, pulled.sum())
    obs.uv[pulled] += np.c_[np.cos(angle), np.sin(angle)] * rng.uniform(1.5, 3.0,
                                                                       (pulled.sum(), 1))
    truth_px = labelled_residual_px(true, obs)
    assert estimate_residual(true, obs).px == pytest.approx(truth_px, rel=0.15)
    assert estimate_residual(true, obs, rounds=3, reproj_widen=1.0).px < 0.8 * truth_px


def test_a_well_calibrated_rig_keeps_the_old_gates_and_figures() -> None:
    """0.1 px: the gates stay at their defaults, estimated or read, so nothing changes."""
    true = sim.make_rig(8, 4.0, seed=1)
    rng = np.random.default_rng(2)
    lo, hi = sim.volume_box(4.0)
    xyz = rng.uniform(lo + 0.1 * (hi - lo), hi - 0.1 * (hi - lo), (10, 50, 3))
    truth = Truth(np.repeat(np.arange(10), 50), np.tile(np.arange(50), 10), xyz.reshape(-1, 3))
    obs = sim.observe(true, truth, noise_px=0.08, dropout=0.2, ghosts_per_camera=2, seed=3)
    found = estimate_residual(true, obs)
    assert found.px == pytest.approx(labelled_residual_px(true, obs), rel=0.3)
    assert found.px < 0.2
    cfg, _ = gated_config(true, obs)
    assert cfg == CorrespondenceConfig()


def test_the_residual_is_read_from_each_calibration_kind(tmp_path) -> None:
    cams = sim.make_rig(3, 4.0, seed=1).cameras
    path = tmp_path / "rig.toml"
    Rig(cams, {"reprojection_rms_px": 0.4, "held_out_rms_px": 0.5, "grade": "good"}).save(path)
    found = rig_residual(Rig.load(path))
    assert found.px == 0.5 and found.detail == "quality.held_out_rms_px"  # the larger
    Rig(cams, {"reprojection_rms_px": 0.4}).save(path)
    assert rig_residual_px(Rig.load(path)) == 0.4
    Rig(cams, {"extrinsic": {"reprojection_rms_px": 0.7}}).save(path)
    assert rig_residual_px(Rig.load(path)) == 0.7
    intr = {"cam0": {"rms_px": 0.1, "points": 100}, "cam1": {"rms_px": 0.3, "points": 300}}
    Rig(cams, {"intrinsic": intr}).save(path)
    assert rig_residual_px(Rig.load(path)) == pytest.approx(np.sqrt((1 + 27) / 400))
    Rig(cams).save(path)
    assert rig_residual_px(Rig.load(path)) is None
    with pytest.raises(UserError, match="non-negative"):
        rig_residual(Rig(cams, {"reprojection_rms_px": -1.0}))


def _write_take(tmp_path, rig_quality: dict, rig_name: str = "rig.toml"):
    """A four-camera take rendered with the true rig, and beside it the rig file of a
    calibration leaving 1 px with `rig_quality` ("recorded": the residual it measured)."""
    true = sim.make_rig(4, 4.0, seed=11)
    est, recorded = miscalibrated(true, 1.0, NOISE_PX, seed=3)
    truth, obs = _take(true, 12, seed=7)
    save_observations(tmp_path / "take.mcrec", obs, truth, true)
    quality = {k: (recorded if v == "recorded" else v) for k, v in rig_quality.items()}
    Rig(est.cameras, quality, dict(est.meta)).save(tmp_path / rig_name)
    return recorded


def _triangulate(tmp_path, calibkit_cli, *extra, rig_name: str = "rig.toml"):
    return calibkit_cli("triangulate", "--rig", tmp_path / rig_name, "--from",
                        tmp_path / "take.mcrec", "--out", tmp_path / "p.csv", "--json",
                        tmp_path / "p.json", *extra)


def test_triangulate_says_which_residual_it_followed(tmp_path, calibkit_cli) -> None:
    recorded = _write_take(tmp_path, {"reprojection_rms_px": "recorded"})
    res = _triangulate(tmp_path, calibkit_cli)
    assert res.code == 0, res.err
    fig = json.loads((tmp_path / "p.json").read_text())
    assert fig["residual"]["source"] == "rig file"
    assert fig["residual"]["px"] == pytest.approx(recorded)
    assert fig["gates"]["epipolar_px"] == pytest.approx(K_EPIPOLAR * recorded)
    assert "quality.reprojection_rms_px" in res.err
    t = fig["truth"]
    assert t["recall_3"] >= 0.95 and t["ghost_fraction"] <= 0.005
    assert "gross errors (> 10 mm)" in res.out and t["gross_errors"] > 0
    # a rig from elsewhere (OpenCV YAML) has no residual: measured on the data, and said so
    _write_take(tmp_path, {}, "rig.yaml")
    res = _triangulate(tmp_path, calibkit_cli, rig_name="rig.yaml")
    assert res.code == 0, res.err
    fig = json.loads((tmp_path / "p.json").read_text())
    assert fig["residual"]["source"] == "estimated from data"
    assert fig["residual"]["px"] == pytest.approx(recorded, rel=0.3)
    assert "estimated from data" in res.err
    # fixed gates on request: the old behaviour
    res = _triangulate(tmp_path, calibkit_cli, "--fixed-gates", rig_name="rig.yaml")
    fig = json.loads((tmp_path / "p.json").read_text())
    assert res.code == 0 and fig["residual"] is None and fig["gates"]["epipolar_px"] == 2.0


def test_bad_residuals_are_one_line_and_exit_2(tmp_path, calibkit_cli) -> None:
    _write_take(tmp_path, {"reprojection_rms_px": -0.5})
    res = _triangulate(tmp_path, calibkit_cli)
    assert res.code == 2
    lines = res.err.strip().splitlines()
    assert len(lines) == 1 and "rig.toml" in lines[0] and "reprojection_rms_px" in lines[0]
    assert not (tmp_path / "p.csv").exists()
    _write_take(tmp_path, {})
    res = _triangulate(tmp_path, calibkit_cli, "--residual-px", "-1")
    assert res.code == 2 and "--residual-px" in res.err


def test_the_daemon_tracker_gates_follow_the_rig_unless_set(tmp_path) -> None:
    from daemon.config.mocapd import load_config
    from daemon.service.daemon import Daemon
    from daemon.tracking.tracker import TrackerConfig

    Rig(sim.make_rig(4, 4.0, seed=1).cameras, {"reprojection_rms_px": 1.5}).save(
        tmp_path / "rig.toml")
    path = tmp_path / "mocapd.toml"
    path.write_text('rig = "rig.toml"\n')
    svc = Daemon(load_config(path))
    cfg = svc._tracker_config(svc.config)
    assert cfg.gate_px == pytest.approx(K_REPROJ * 1.5)
    assert cfg.outlier_px == pytest.approx(K_REPROJ * 1.5)
    assert cfg.ambiguous_px == pytest.approx(K_REPROJ * 1.5)  # crossing markers' margin
    assert cfg.correspondence.epipolar_px == pytest.approx(K_EPIPOLAR * 1.5)
    assert cfg.correspondence.two_camera is False  # the rest of the tracker's own choice
    path.write_text('rig = "rig.toml"\n[tracker]\ngate_px = 3.5\n')
    svc = Daemon(load_config(path))
    cfg = svc._tracker_config(svc.config)
    assert cfg.gate_px == 3.5 and cfg.outlier_px == pytest.approx(K_REPROJ * 1.5)
    Rig(sim.make_rig(4, 4.0, seed=1).cameras).save(tmp_path / "rig.toml")
    svc = Daemon(load_config(path))
    assert svc._tracker_config(svc.config).outlier_px == TrackerConfig().outlier_px
