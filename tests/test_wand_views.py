"""The intrinsic step's monitor views in the wand's graph (calibkit.calibrate.plane_views and
calibkit.calibrate.bundle.TargetData), against the simulator's truth."""

from __future__ import annotations

import numpy as np
import pytest

from calibkit.calibrate import plane_views
from calibkit.calibrate.intrinsic import PlaneView, calibrate, monitor_plane_view
from calibkit.calibrate.wand_solve import calibrate as calibrate_wand
from calibkit.core.camera import Rig
from calibkit.synthetic import sim
from calibkit.synthetic.miscalibrate import off_intrinsics
from calibkit.synthetic.monitor import MonitorSimConfig, make_monitor_sim, projected_dots
from projector.patterns import coded_schedule

SPACING = (0.0, 0.2, 0.5)
NOISE_PX = 0.05  # the monitor's centroid noise per axis


def _monitor(cam, seed: int) -> tuple[list[PlaneView], float]:
    """Six views of the simulated monitor (coded dots every 80 screen px) as the capture
    reports them, and the dots' radius on the screen (metres) for the bias correction."""
    cfg = MonitorSimConfig(seed=seed)
    schedule = coded_schedule(cfg.screen_px, 80.0, 2, 6.0)
    rng = np.random.default_rng(seed)
    pitch = cfg.pixel_pitch_mm
    with make_monitor_sim(6, cam.size, seed, cfg, camera=cam, fill=0.8) as monitor:
        views = [monitor_plane_view(projected_dots(cam, view, schedule.points_xy,
                                                   schedule.radius_px, pitch, NOISE_PX, rng),
                                    schedule, pitch) for view in monitor.views]
    return views, schedule.radius_px * pitch / 1000.0


@pytest.fixture(scope="module")
def monitored():
    """A 4-camera rig, each camera's monitor views and the intrinsic step's result on them."""
    rig = sim.make_rig(4, 4.0, seed=3)
    views = None
    for k, cam in enumerate(rig):
        mv, radius_m = _monitor(cam, 40 + k)
        result = calibrate(mv, cam.size, cam.name, dot_radius_m=radius_m)
        one = plane_views.from_result(cam.name, result.views, result)
        views = plane_views.merge(views, one)
    return rig, views


def test_views_file_round_trip_merge_and_rebase(monitored, tmp_path):
    rig, views = monitored
    path = tmp_path / "a" / "intr.views.npz"
    path.parent.mkdir()
    plane_views.save(path, views)
    back = plane_views.load(path)
    assert back.camera_names == views.camera_names
    assert np.array_equal(back.uv, views.uv) and np.array_equal(back.view, views.view)
    # a camera calibrated again replaces its own rows only
    again = views.cameras(["cam1"])
    merged = plane_views.merge(back, again)
    assert sorted(merged.camera_names) == sorted(views.camera_names)
    assert len(merged) == len(views) and len(merged.view_camera) == len(views.view_camera)
    # subsets renumber cameras and views to the order asked for
    sub = views.cameras(["cam2", "cam0"])
    assert sub.camera_names == ("cam2", "cam0")
    assert np.array_equal(np.unique(sub.view_camera), [0, 1]) and len(sub.view_camera) == 12
    # a rig file written elsewhere still finds the views
    (tmp_path / "b").mkdir()
    quality = {"intrinsic": {n: {"views_file": path.name} for n in views.camera_names}}
    moved = plane_views.rebase(quality, path.parent / "intr.toml", tmp_path / "b" / "ext.toml")
    assert moved["intrinsic"]["cam0"]["views_file"] == "../a/intr.views.npz"
    found = plane_views.load_for(moved, tmp_path / "b" / "ext.toml", ["cam0", "cam3"])
    assert found.camera_names == ("cam0", "cam3") and len(found.view_camera) == 12
    assert plane_views.load_for({}, tmp_path / "b" / "ext.toml", ["cam0"]) is None


def test_monitor_views_set_the_intrinsics_the_wand_alone_cannot(monitored):
    """An intrinsics file 0.5 % / 2 px off, solved with a short wand dance: with the monitor
    views in the graph the intrinsics come back to the truth (the views determine them to
    ~0.01 %, ~0.05 px), while with the file's priors alone they stay off (the wand reaches
    little of each image)."""
    rig, views = monitored
    truth = sim.wand_motion(400, 100.0, 4.0, SPACING, seed=3)
    obs = sim.observe(rig, truth, noise_px=0.1, seed=3)
    off = off_intrinsics(rig, 0.005, 2.0, 0.0, np.random.default_rng(3))
    errs = {}
    for label, tv in (("views", views), ("priors", None)):
        cal = calibrate_wand(obs, off, SPACING, initial=off, holdout=0.0, seed=3,
                             target_views=tv)
        focal = max(abs(c.fx / t.fx - 1) for c, t in zip(cal.rig, rig, strict=True))
        centre = max(np.hypot(c.cx - t.cx, c.cy - t.cy) for c, t in zip(cal.rig, rig,
                                                                         strict=True))
        errs[label] = (focal, centre)
        rows = cal.report["intrinsics"]["cameras"]
        if tv is not None:
            assert all(r["prior_from"] == "intrinsic step's views" for r in rows)
            # every view's dots fit at the monitor's noise (RMS per axis)
            assert all(r["views_rms_px"] < 1.3 * NOISE_PX for r in rows)
            assert cal.bundle.target_noise_px == pytest.approx(NOISE_PX, rel=0.25)
    assert errs["views"][0] < 3e-4 and errs["views"][1] < 0.3
    assert errs["priors"][0] > 2 * errs["views"][0] or errs["priors"][1] > 2 * errs["views"][1]


def test_views_are_left_out_when_the_intrinsics_are_held(monitored):
    rig, views = monitored
    truth = sim.wand_motion(200, 100.0, 4.0, SPACING, seed=4)
    obs = sim.observe(rig, truth, noise_px=0.1, seed=4)
    cal = calibrate_wand(obs, rig, SPACING, initial=rig, holdout=0.0, refine_intrinsics=False,
                         target_views=views)
    assert cal.bundle.target is None
    assert all(c.fx == t.fx for c, t in zip(cal.rig, rig, strict=True))
    assert isinstance(cal.rig, Rig)


def test_view_factor_jacobians_match_finite_differences():
    """The per-view factor's analytic Jacobians (pose on the right, Cal3DS2 additive)."""
    import gtsam

    from calibkit.calibrate.bundle_target import _project

    rng = np.random.default_rng(0)
    pose = gtsam.Pose3(gtsam.Rot3.Rodrigues(0.3, -0.2, 0.1), np.array([0.1, -0.05, -0.6]))
    cal = gtsam.Cal3DS2(520.0, 515.0, 0.0, 321.0, 238.0, -0.2, 0.08, 0.001, -0.002)
    xyz = np.column_stack([rng.uniform(-0.2, 0.2, (20, 2)), np.zeros(20)])
    uv, d_pose, d_cal = _project(pose, cal, xyz, True)
    h = 1e-6
    for k in range(6):
        xi = np.zeros(6)
        xi[k] = h
        num = (_project(pose.retract(xi), cal, xyz, False)[0] - uv) / h
        assert np.allclose(num, d_pose[:, :, k], atol=1e-3 * np.abs(num).max() + 1e-6)
    for k in range(9):
        dv = np.zeros(9)
        dv[k] = h
        num = (_project(pose, gtsam.Cal3DS2(cal.vector() + dv), xyz, False)[0] - uv) / h
        assert np.allclose(num, d_cal[:, :, k], atol=1e-3 * np.abs(num).max() + 1e-6)
