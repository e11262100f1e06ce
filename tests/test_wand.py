"""Wand identification, capture coverage, initial poses from nothing, the floor frame and the
report's checks and held-out figures, against the simulator's truth."""

from __future__ import annotations

import numpy as np
import pytest

from calibkit.calibrate import floor, wand_report
from calibkit.calibrate.wand import CaptureMonitor, WandSpec, identify, initial_poses
from calibkit.calibrate.wand_solve import calibrate
from calibkit.core.camera import Rig, rotation_from_rvec
from calibkit.core.errors import UserError
from calibkit.core.geometry import rigid_fit
from calibkit.core.observations import Observations, Truth
from calibkit.synthetic import sim
from calibkit.synthetic.miscalibrate import off_intrinsics

SPACING = (0.0, 0.2, 0.5)


@pytest.fixture(scope="module")
def scene():
    rig = sim.make_rig(5, 4.0, seed=11)
    truth = sim.wand_motion(500, 100.0, 4.0, SPACING, seed=11)
    obs = sim.observe(rig, truth, noise_px=0.2, ghosts_per_camera=0.5, seed=11)
    return rig, truth, obs


def _true_markers(obs: Observations, wand) -> np.ndarray:
    """The simulator's marker id of each identified row (matched by frame, camera, pixel)."""
    key_o = np.lexsort((obs.uv[:, 1], obs.uv[:, 0], obs.camera, obs.frame))
    ko = np.stack([obs.frame, obs.camera, obs.uv[:, 0], obs.uv[:, 1]], axis=1)[key_o]
    kw = np.stack([wand.frame, wand.camera, wand.uv[:, 0], wand.uv[:, 1]], axis=1)
    idx = [np.flatnonzero(np.all(ko == row, axis=1))[0] for row in kw[:200]]
    return obs.marker[key_o][idx]


def test_identify_labels_the_wand_among_stray_blobs(scene):
    rig, _truth, obs = scene
    w = identify(obs, WandSpec(SPACING), rig)
    # every label is right: rows are never guessed
    assert np.array_equal(_true_markers(obs, w), w.marker[:200])
    assert np.all(obs.marker[np.isin(obs.uv[:, 0], w.uv[:, 0])] >= 0)  # no ghost taken
    # most (frame, camera) groups that show the whole wand are identified; the rest are
    # foreshortened views or stray blobs lined up with it
    full = np.bincount((obs.frame * 10 + obs.camera)[obs.marker >= 0]) == 3
    found = len(w) // 3
    assert found > 0.85 * full.sum()
    assert sum(w.stats["ambiguous"]) > 0  # stray blobs did make some groups ambiguous


def test_identify_rejects_a_group_with_two_wands():
    spec = WandSpec(SPACING)
    uv = np.array([[100, 100], [140, 100], [200, 100], [100, 300], [140, 300], [200, 300],
                   [400, 400], [440, 400], [500, 400]], dtype=float)
    n = len(uv)
    frame = np.r_[np.zeros(6), np.ones(3)]
    obs = Observations(("c",), ((640, 480),), frame, np.zeros(n), np.zeros(n), uv,
                       np.ones(n), np.ones(n))
    w = identify(obs, spec)
    assert list(w.frames()) == [1]  # frame 0 has two wands: ambiguous, dropped
    assert list(w.marker) == [0, 1, 2] and w.uv[0, 0] == 400 and w.uv[2, 0] == 500
    flipped = obs.select(np.arange(6, 9))
    flipped.uv = flipped.uv[::-1] * [-1, 1] + [1000, 0]  # the wand the other way round
    w2 = identify(flipped, spec)
    assert w2.uv[0, 0] == 600 and w2.uv[2, 0] == 500


def test_wand_spec_rejects_what_cannot_be_identified():
    with pytest.raises(UserError):
        WandSpec((0.0, 0.25, 0.5))  # equal spacings: the ends look alike
    with pytest.raises(UserError):
        WandSpec((0.0, 0.5, 0.2))
    with pytest.raises(UserError):
        WandSpec((0.0, 0.1, 0.2, 0.5))
    assert WandSpec((0.0, 0.5)).edges()[1].tolist() == [0.5]


def test_one_marker_wand_takes_single_blobs():
    rig = sim.make_rig(3, 4.0, seed=2)
    truth = sim.wand_motion(50, 100.0, 4.0, (0.0,), seed=2)
    obs = sim.observe(rig, truth, noise_px=0.1, seed=2)
    w = identify(obs, WandSpec((0.0,)), rig)
    assert len(w) == len(obs) and np.all(w.marker == 0)


def test_capture_monitor_stops_when_every_camera_has_enough(scene):
    rig, _truth, obs = scene
    spec = WandSpec(SPACING)
    monitor = CaptureMonitor(rig.names, [c.size for c in rig], min_samples=100,
                             min_coverage=0.1)
    assert not monitor.done()
    w = identify(obs, spec, rig)
    monitor.add(w.select(w.frame < 50))
    assert not monitor.done()  # fewer than 100 samples per camera yet
    monitor.add(w.select(w.frame >= 50))
    assert monitor.done()
    assert np.array_equal(monitor.samples, np.bincount(w.camera[w.marker == 0]))
    # coverage: a grid cell is filled once a marker fell in it
    m = CaptureMonitor(["a"], [(640, 480)], grid=8)
    assert m.gy == 6
    u, v = np.meshgrid(np.arange(8) * 80 + 5, np.arange(6) * 80 + 5)
    from calibkit.calibrate.wand import WandObservations

    pts = np.stack([u.ravel(), v.ravel()], axis=1).astype(float)
    m.add(WandObservations(("a",), ((640, 480),), np.arange(len(pts)), np.zeros(len(pts),
                           dtype=np.int32), np.zeros(len(pts), dtype=np.int32), pts))
    assert m.coverage[0] == 1.0
    assert m.grid_text().splitlines()[1:] == ["########"] * 6
    assert set("".join(monitor.grid_text().splitlines()[1:]).replace(" ", "")) <= {"#", "."}


def test_initial_poses_from_nothing(scene):
    rig, _truth, obs = scene
    spec = WandSpec(SPACING)
    placed, missing = initial_poses(identify(obs, spec, rig), rig, spec)
    assert missing == [] and placed.names == rig.names
    est, true = placed.centres(), rig.centres()
    R, t, s = rigid_fit(est, true, scale=True)
    # the scale comes from the wand's median length: within 1 %
    assert abs(s - 1) < 0.01
    # exact without noise (checked by hand: 1e-11 m); with 0.2 px and stray blobs a start
    # for the bundle adjustment within 2.5 % of the 4 m volume, from which it converges
    # (test_held_out_figures_match_the_solved_ones solves from this very start)
    assert np.max(np.linalg.norm(est @ R.T + t - true, axis=1)) < 0.1


def test_floor_from_an_lframe():
    rig = sim.make_rig(5, 4.0, seed=3)
    lframe = floor.LFrame()
    pts = lframe.points((0.3, -0.2), 0.4)
    n = 30
    truth = Truth(np.repeat(np.arange(n), 3), np.tile(np.arange(3), n), np.tile(pts, (n, 1)))
    obs = sim.observe(rig, truth, noise_px=0.1, ghosts_per_camera=0.3, seed=1)
    moved = floor.transform_rig(rig, rotation_from_rvec([0.1, -0.2, 0.7]), np.array([1, 2, 0]))
    A, b = floor.world_from_recording(moved, obs, "lframe", lframe)
    back = floor.transform_rig(moved, A, b)
    expected = floor.transform_rig(rig, *floor.frame_from_lframe(*pts, lframe))
    # 0.1 px over 30 frames puts each marker ~0.1 mm off; over the 0.3 m arm that tilts the
    # frame ~0.5 mrad, ~2 mm at the cameras' 3-4 m
    err = np.linalg.norm(back.centres() - expected.centres(), axis=1)
    assert err.max() < 5e-3
    assert np.all(back.centres()[:, 2] > 1.0)  # cameras above the floor, z up


def test_floor_from_the_wand_laid_twice_and_from_plane_points():
    rig = sim.make_rig(5, 4.0, seed=4)
    h = floor.LFRAME_MARKER_RADIUS_M
    first = np.array([[0.0, 0.0, h], [0.2, 0.0, h], [0.5, 0.0, h]])
    second = np.array([[-0.5, 0.5, h], [-0.5, 0.7, h], [-0.5, 1.0, h]])
    n = 20
    xyz = np.concatenate([np.tile(first, (n, 1)), np.tile(second, (n, 1))])
    truth = Truth(np.repeat(np.arange(2 * n), 3), np.tile(np.arange(3), 2 * n), xyz)
    obs = sim.observe(rig, truth, noise_px=0.1, seed=4)
    A0, b0 = rotation_from_rvec([0.05, 0.1, -0.3]), np.array([0.0, 1.0, 2.0])
    moved = floor.transform_rig(rig, A0, b0)
    A, b = floor.world_from_recording(moved, obs, "wand", spacing_m=SPACING)
    back = floor.transform_rig(moved, A, b)
    assert np.max(np.linalg.norm(back.centres() - rig.centres(), axis=1)) < 5e-3
    # projector dots on the floor: the floor plane and z up (x, y are the dots' own)
    dots = np.random.default_rng(0).uniform([-1.5, -1.5, 0], [1.5, 1.5, 0], (40, 3))
    A2, b2 = floor.frame_from_plane_points(floor.transform_points(dots, A0, b0), moved)
    heights = floor.transform_rig(moved, A2, b2).centres()[:, 2]
    assert np.allclose(heights, rig.centres()[:, 2], atol=1e-6)
    with pytest.raises(UserError):
        floor.frame_from_wand_on_floor([(first[0], first[2])], rig)


@pytest.fixture(scope="module")
def calibrated(scene):
    rig, _truth, obs = scene
    return rig, calibrate(obs, rig, SPACING, holdout=0.1, seed=1)


def test_held_out_figures_match_the_solved_ones(calibrated):
    rig, cal = calibrated
    held, solved = cal.report["held_out"], cal.report["solve"]
    assert held["frames"] == pytest.approx(0.1 * (held["frames"] + solved["frames"]), abs=2)
    # frames the solve never saw fit about as well: no over-fitting (0.2 px noise per axis,
    # so ~0.28 px per 2D residual, less what triangulation absorbs)
    assert 0.15 < held["reprojection_rms_px"] < 0.3
    assert held["reprojection_rms_px"] < 1.2 * solved["reprojection_rms_px"]
    # wand lengths are unbiased; their spread is the triangulation noise of single frames
    assert abs(held["wand_length_error_mean_mm"]) < 3 * held["wand_length_error_sd_mm"] / \
        np.sqrt(held["frames"]) + 0.05
    assert cal.report["grade"] in ("excellent", "good")
    assert cal.report["checks"]["ok"]
    for cam in cal.report["cameras"]:
        assert cam["held_out_rms_px"] < 0.35


def test_impossible_solutions_are_flagged(calibrated):
    _rig, cal = calibrated
    xyz = cal.solved["xyz"]
    ok = wand_report.checks(cal.rig, xyz, 0.0)
    assert ok["ok"]
    # a camera turned to face away from the volume
    cam = cal.rig[1]
    away = cal.rig.replace_camera(cam.replace(R=rotation_from_rvec([0, np.pi, 0]) @ cam.R,
                                              t=rotation_from_rvec([0, np.pi, 0]) @ cam.t))
    found = wand_report.checks(away, xyz, 0.0)
    assert found["camera_behind_volume"] and found["cameras_behind"] == [cam.name]
    # the world upside down: turned 180 degrees about x
    A = rotation_from_rvec([np.pi, 0, 0])
    flipped = wand_report.checks(floor.transform_rig(cal.rig, A, np.zeros(3)), xyz @ A.T, 0.0)
    assert flipped["upside_down"] and not flipped["ok"]
    # the "twisted pair": a camera turned 180 degrees about its baseline to another one
    # explains the same epipolar geometry, but the markers then triangulate behind cameras
    c0, c1 = cal.rig[0].centre, cal.rig[1].centre
    axis = (c1 - c0) / np.linalg.norm(c1 - c0)
    half_turn = rotation_from_rvec(np.pi * axis)
    twisted_cam = cal.rig[1].replace(R=cal.rig[1].R @ half_turn.T)
    twisted_cam = twisted_cam.replace(t=-twisted_cam.R @ c1)
    twisted = cal.rig.replace_camera(twisted_cam)
    camera_of = np.array([twisted.index(n) for n in cal.wand.camera_names])
    fig = wand_report.evaluate(twisted, cal.wand, WandSpec(SPACING), None, camera_of)
    assert fig["behind_share"] > wand_report.BEHIND_SHARE
    assert wand_report.checks(twisted, fig["xyz"], fig["behind_share"])["mirrored"]
    assert cal.solved["behind_share"] == 0.0
    grade, reason = wand_report.grade(cal.report["held_out"], flipped, 0.5)
    assert grade == "failed" and "upside down" in reason


def test_two_marker_wand_with_initial_poses_and_from_nothing():
    rig = sim.make_rig(4, 4.0, seed=12)
    spacing = (0.0, 0.5)
    truth = sim.wand_motion(300, 100.0, 4.0, spacing, seed=12)
    obs = sim.observe(rig, truth, noise_px=0.2, seed=12)
    start = Rig(tuple(c.replace(t=c.t + np.random.default_rng(0).normal(0, 0.01, 3))
                      for c in rig))
    # the true intrinsics, held: this is about the labels and the start (the intrinsics'
    # refinement is tested on a scene of the size it needs, below)
    cal = calibrate(obs, rig, spacing, initial=start, seed=0, refine_intrinsics=False)
    # labels made consistent across cameras: the wand's length comes out right
    assert abs(cal.report["held_out"]["wand_length_error_mean_mm"]) < 1.0
    assert cal.report["held_out"]["reprojection_rms_px"] < 0.35
    # from nothing: poses from the blobs' midpoints, labels from those poses, solved twice
    cal = calibrate(obs, rig, spacing, seed=0, refine_intrinsics=False)
    held = cal.report["held_out"]
    # unbiased within the spread of 30 held-out frames' lengths
    assert abs(held["wand_length_error_mean_mm"]) < 3 * held["wand_length_error_sd_mm"] / \
        np.sqrt(held["frames"])
    assert held["reprojection_rms_px"] < 0.35
    est, true = cal.rig.centres(), rig.centres()
    R, t, s = rigid_fit(est, true, scale=True)
    assert abs(s - 1) < 2e-3 and np.max(np.linalg.norm(est @ R.T + t - true, axis=1)) < 5e-3


def test_one_marker_wand_needs_initial_poses_for_its_scale():
    rig = sim.make_rig(4, 4.0, seed=13)
    truth = sim.wand_motion(300, 100.0, 4.0, (0.0,), seed=13)
    obs = sim.observe(rig, truth, noise_px=0.2, seed=13)
    with pytest.raises(UserError, match="scale"):
        calibrate(obs, rig, (0.0,))  # one marker, no poses: nothing gives the scale
    rng = np.random.default_rng(1)
    turned = [c.replace(rvec=c.rvec + rng.normal(0, 0.003, 3)) for c in rig]
    start = Rig(tuple(t.replace(t=-t.R @ c.centre) for t, c in zip(turned, rig, strict=True)))
    cal = calibrate(obs, rig, (0.0,), initial=start)
    assert cal.report["held_out"]["reprojection_rms_px"] < 0.35
    # the pixels fit, but a single marker's rays leave the cameras loosely determined
    # (position SDs of 15-25 mm here, the rig ~6 mm off): the grade says so
    assert cal.report["grade"] == "usable" and "ppm" in cal.report["grade_reason"]
    # the scale is held at the starting rig's (true) size; a single marker gives rays only,
    # so the shape is known less well (exact without noise, checked by hand) and the
    # reported uncertainty says so: the errors are of its size
    est, true = cal.rig.centres(), rig.centres()
    R, t, _ = rigid_fit(est, true)
    err_mm = 1000 * np.linalg.norm(est @ R.T + t - true, axis=1)
    std_mm = np.array([c["position_std_mm"] for c in cal.report["cameras"]])
    assert std_mm.max() < 50
    assert err_mm.max() < 3 * std_mm.max()


def test_capture_keeps_what_it_has_on_ctrl_c(scene):
    from calibkit.calibrate.wand_pipeline import capture
    from calibkit.clitools import Progress

    rig, _truth, obs = scene

    def batches():
        yield obs.select(obs.frame < 50)
        yield obs.select((obs.frame >= 50) & (obs.frame < 100))
        raise KeyboardInterrupt

    monitor = CaptureMonitor(rig.names, [c.size for c in rig], min_samples=10**6)
    got = capture(batches(), WandSpec(SPACING), rig, monitor, None,
                  Progress("capture", enabled=False))
    assert got is not None and list(got.frames()) == list(range(100))
    assert monitor.samples.sum() > 0 and not monitor.done()


def test_projector_dots_join_the_wand_solve_and_hold_the_world_frame():
    from calibkit.calibrate import bundle

    rig = sim.make_rig(4, 4.0, seed=14)
    truth = sim.wand_motion(300, 100.0, 4.0, SPACING, seed=14)
    obs = sim.observe(rig, truth, noise_px=0.2, seed=14)
    projector = sim.make_projector(4.0, seed=14)
    u, v = np.meshgrid(np.linspace(100, 1180, 8), np.linspace(100, 700, 6))
    xyz, plane = sim.projector_scene(projector, np.stack([u.ravel(), v.ravel()], axis=1))
    xyz = xyz[plane == 0]
    dots = sim.observe(rig, Truth(np.zeros(len(xyz)), np.arange(len(xyz)), xyz),
                       noise_px=0.2, seed=15)

    def extra(start: Rig) -> bundle.BundleData:
        cam = np.array([start.names.index(n) for n in dots.camera_names])[dots.camera]
        pts = np.arange(len(xyz))
        return bundle.BundleData(start, dots.marker, cam, dots.uv, xyz, known_point=pts,
                                 known_xyz=xyz, plane_point=pts,
                                 plane_normal=np.tile([0.0, 0.0, 1.0], (len(xyz), 1)),
                                 plane_offset_m=np.zeros(len(xyz)))

    rng = np.random.default_rng(3)
    start = Rig(tuple(c.replace(t=c.t + rng.normal(0, 0.02, 3)) for c in rig))
    cal = calibrate(obs, rig, SPACING, initial=start, extra=extra, refine_intrinsics=False)
    assert cal.report["world_frame"] == "floor"
    # the dots' surveyed positions (1 mm) hold the frame: no alignment needed
    err = np.linalg.norm(cal.rig.centres() - rig.centres(), axis=1)
    assert err.max() < 5e-3
    with pytest.raises(UserError, match="world frame"):
        calibrate(obs, rig, SPACING, extra=extra)


# ---- intrinsics as an intrinsic calibration leaves them ------------------------------------

def _off_intrinsics(rig: Rig, focal_rel: float, centre_px: float, k1: float) -> Rig:
    return off_intrinsics(rig, focal_rel, centre_px, k1, np.random.default_rng(5))


@pytest.fixture(scope="module")
def six_cameras():
    rig = sim.make_rig(6, 4.0, seed=3)
    truth = sim.wand_motion(700, 100.0, 4.0, SPACING, seed=3)
    return rig, sim.observe(rig, truth, noise_px=0.1, seed=3)


def test_grade_sees_wrong_intrinsics_that_the_pixels_hide(six_cameras):
    from calibkit.calibrate.compare import compare_rigs

    rig, obs = six_cameras
    good = calibrate(obs, rig, SPACING, refine_intrinsics=False, seed=0)
    assert compare_rigs(rig, good.rig)["grid_rms_mm"] < 0.3
    assert good.report["grade"] == "excellent", good.report["grade_reason"]
    off = _off_intrinsics(rig, 0.005, 2.0, 0.005)
    bad = calibrate(obs, off, SPACING, refine_intrinsics=False, seed=0)
    assert compare_rigs(rig, bad.rig)["grid_rms_mm"] > 1.0
    # the pixels alone would pass it as 'good' at least ...
    held = bad.report["held_out"]
    assert held["reprojection_rms_px"] < wand_report.GRADES[1][1]
    # ... the length's variation across the image does not
    assert bad.report["grade"] not in ("excellent", "good"), bad.report["grade_reason"]
    assert "warped" in bad.report["grade_reason"]
    worst = max(bad.report["systematic"][k] for k in ("volume_pct", "radius_pct", "region_pct"))
    assert worst > 2.5 * wand_report.SYSTEMATIC_GRADES[0][1]
    assert max(good.report["systematic"][k] for k in ("volume_pct", "radius_pct",
                                                      "region_pct")) <= \
        wand_report.SYSTEMATIC_GRADES[0][1]
    # refined (the default) from the same wrong intrinsics: back within a millimetre
    refined = calibrate(obs, off, SPACING, seed=0)
    assert refined.report["intrinsics"]["refined"]
    assert compare_rigs(rig, refined.rig)["grid_rms_mm"] < 1.0
    assert refined.report["grade"] in ("excellent", "good")


def test_held_out_frames_come_at_random_and_in_whole_regions():
    rng = np.random.default_rng(0)
    frames = np.arange(2000)
    centre = rng.uniform(-1, 1, (2000, 3))
    centre[:50] = np.nan  # frames not triangulated: only the random share may take them
    random, region = wand_report.hold_out(frames, centre, 0.1, seed=1)
    assert len(np.intersect1d(random, region)) == 0
    assert abs(len(random) + len(region) - 200) <= 1 and len(region) >= 100
    # the regions are whole cells: a box around them holds no frame that was kept
    inside = centre[region]
    lo, hi = np.nanmin(inside, axis=0), np.nanmax(inside, axis=0)
    boxed = np.all((centre >= lo) & (centre <= hi), axis=1)
    assert np.mean(np.isin(frames[boxed], region)) > 0.5


def test_intrinsic_priors_from_the_rig_file():
    from calibkit.calibrate import intrinsic_prior as ip

    rig = sim.make_rig(2, 4.0, seed=1)
    std = {"fx": 0.02, "fy": 0.02, "cx": 0.03, "cy": 0.03, "skew": 0.0, "k1": 0.0001,
           "k2": 0.5, "p1": 1e-5, "p2": 1e-5, "k3": 1.0}
    rig = Rig(rig.cameras, {"intrinsic": {"cam0": {"rms_px": 0.05, "std": std}}})
    sigma, source = ip.prior_sigmas(rig)
    assert source == ["intrinsic step", "default"]
    f = 0.5 * (rig[0].fx + rig[0].fy)
    # tiny reported sigmas are floored at what calibrations really leave; a k2 made loose
    # by its trade-off with k3 (held here) is capped
    assert sigma[0, 0] == pytest.approx(ip.FLOOR["focal_rel"] * f)
    assert sigma[0, 3] == ip.FLOOR["centre_px"] and sigma[0, 5] == ip.FLOOR["radial"]
    assert sigma[0, 6] == ip.DEFAULT["radial"]
    assert sigma[1, 0] == pytest.approx(ip.DEFAULT["focal_rel"] * 0.5 * (rig[1].fx + rig[1].fy))
    big = dict(std, fx=1.0)  # a reported 1 px: inflated to 3 px
    sigma, _ = ip.prior_sigmas(Rig(rig.cameras, {"intrinsic": {"cam0": {"std": big}}}))
    assert sigma[0, 0] == pytest.approx(ip.INFLATE * 1.0)
    # a lens model that folds over inside the image is caught
    folding = rig[0].replace(dist=[0.0, -2.0, 0, 0, 0])
    assert ip.folds_over(folding, 0.8) and not ip.folds_over(rig[0], 0.8)
    rows, warnings = ip.check_refined(Rig((rig[0],)), Rig((folding,)), sigma[:1])
    assert rows[0]["largest_change_parameter"] == "k2" and len(warnings) == 2
