"""calibkit.calibrate.extrinsic_* against the simulated projector's truth
(calibkit.synthetic.projector)."""

from __future__ import annotations

import numpy as np
import pytest

from calibkit.calibrate import extrinsic_capture as exc
from calibkit.calibrate import extrinsic_reference as exr
from calibkit.calibrate import extrinsic_report as exp
from calibkit.calibrate import extrinsic_solve as exs
from calibkit.calibrate.compare import compare_rigs
from calibkit.core.camera import Rig, look_at, rvec_from_rotation
from calibkit.core.errors import UserError
from calibkit.synthetic import projector as sp
from calibkit.synthetic.extrinsic_sim import TAPE_HEIGHT_ERROR_MM
from projector.patterns import coded_schedule

PROJ = (1280, 800)


def _refs(scene, error_m=0.005, seed=0, n=4, height_error_m=None):
    """The tape's reference points and table height (error: error_m per axis, and the
    simulator's tape height error, TAPE_HEIGHT_ERROR_MM, unless given)."""
    if height_error_m is None:
        height_error_m = TAPE_HEIGHT_ERROR_MM / 1000.0 if error_m > 0 else 0.0
    m = sp.measured_references(scene, exr.reference_layout_px(PROJ, n),
                               sp.table_reference_px(scene) if scene.table else np.zeros((0, 2)),
                               error_m, height_error_m, seed=seed)
    return exr.References(m["floor_px"], m["floor_xy_m"], m.get("table_px", np.zeros((0, 2))),
                         m.get("table_xy_m", np.zeros((0, 2))), m.get("table_height_m"))


def _dots(scene, refs, noise_px=0.2, seed=0, wrong_ids=0.0, step=64.0):
    sch = coded_schedule(PROJ, step, 2, 8)
    floor, table = exr.plane_maps(refs)
    fd = sp.simulated_dots(scene, sch.points_xy, False, noise_px, wrong_ids, seed=seed)
    td = None
    if table is not None:
        tsch = exr.table_schedule(sch, table)
        td = sp.simulated_dots(scene, sch.points_xy, True, noise_px, wrong_ids, seed=seed + 1,
                               shown=np.concatenate(tsch.layers))
    return sch, floor, table, fd, td


def _errors(truth: Rig, rig: Rig):
    cmp = compare_rigs(truth, rig, align=False)
    return ({c["name"]: c["position_mm"] for c in cmp["cameras"]},
            {c["name"]: c["rotation_deg"] for c in cmp["cameras"]})


# ---- plane maps ---------------------------------------------------------------------------------

def test_homography_is_exact_for_a_distortion_free_projector():
    scene = sp.make_scene(2, seed=3)
    proj = scene.projector.replace(dist=np.zeros(5))
    scene = sp.ProjectorScene(scene.rig, proj, scene.table)
    refs = _refs(scene, error_m=0.0)
    floor, _ = exr.plane_maps(refs)
    px = coded_schedule(PROJ, 64, 1, 8).points_xy
    truth, plane = scene.land(px, table_present=False)
    got = floor.apply(px)
    assert np.all(plane == 0)
    assert np.max(np.linalg.norm(got - truth, axis=1)) < 1e-6
    assert floor.residual_rms_mm < 1e-3


def test_homography_residual_matches_the_tape_error():
    """16 points with 5 mm error per axis: the 8-parameter fit leaves an RMS (2D) residual
    of sigma * sqrt(2 (2N - 8) / 2N) = 6.1 mm; 24 degrees of freedom spread it by ~15 %."""
    scene = sp.make_scene(2, seed=1)
    sigma = 0.005
    rms = [exr.plane_maps(_refs(scene, sigma, seed=s))[0].residual_rms_mm for s in range(6)]
    expected = 1000 * sigma * np.sqrt(2 * 24 / 32)
    assert 0.75 * expected < np.mean(rms) < 1.25 * expected
    # the map puts dots within a few tape errors of where they land (plus the lens's bend)
    floor, _ = exr.plane_maps(_refs(scene, sigma, seed=0))
    px = coded_schedule(PROJ, 64, 1, 8).points_xy
    truth, _ = scene.land(px, table_present=False)
    assert np.sqrt(np.mean(np.sum((floor.apply(px) - truth) ** 2, axis=1))) < 3 * sigma


def test_reference_points_on_a_line_or_too_few_are_refused():
    px = np.array([[0, 0], [100, 100], [200, 200], [300, 300.0]])
    with pytest.raises(UserError, match="on a line"):
        exr.fit_homography(px, px / 100.0)
    with pytest.raises(UserError, match="at least 4"):
        exr.fit_homography(px[:3], px[:3] / 100.0)


def test_table_dots_land_on_the_table():
    scene = sp.make_scene(2, seed=0)
    refs = _refs(scene, 0.005)
    floor, table = exr.plane_maps(refs)
    sch = exr.table_schedule(coded_schedule(PROJ, 64, 2, 8), table)
    ids = np.concatenate(sch.layers)
    truth, plane = scene.land(sch.points_xy[ids], table_present=True)
    assert len(ids) > 50
    assert np.all(plane == exr.TABLE)  # none falls off the edge
    got, got_plane = exr.dot_world_points(sch.points_xy[ids], floor, table, True)
    assert np.all(got_plane == exr.TABLE)
    # on the tape's table top, which is not the true one
    assert np.max(np.abs(got[:, 2] - refs.table_height_m)) < 1e-12
    assert refs.table_height_m != scene.table.height_m
    assert np.max(np.linalg.norm(got - truth, axis=1)) < 0.02


# ---- reference files ----------------------------------------------------------------------------

def test_reference_file_round_trip(tmp_path):
    scene = sp.make_scene(2, seed=0)
    refs = _refs(scene)
    path = tmp_path / "refs.toml"
    path.write_text(exr.references_toml(refs, "test"))
    back = exr.load_references(path)
    assert np.allclose(back.floor_px, refs.floor_px, atol=0.05)
    assert np.allclose(back.floor_xy_m, refs.floor_xy_m, atol=1e-4)
    assert np.allclose(back.table_xy_m, refs.table_xy_m, atol=1e-4)
    assert back.table_height_m == pytest.approx(refs.table_height_m, abs=1e-4)


@pytest.mark.parametrize("text, message", [
    ("[[floor]]\npx = [1, 2]\nxy_m = [0, 0]\n", "at least 4 are needed"),
    ("".join(f"[[floor]]\npx = [{u}, {v}]\nxy_m = [{u / 100}, {v / 100}]\n"
             for u, v in ((0, 0), (500, 0), (0, 500), (500, 500)))
     + "".join(f"[[table.point]]\npx = [{u}, {v}]\nxy_m = [{u}, {v}]\n"
               for u, v in ((1, 1), (2, 1), (1, 2), (2, 2))), "not the table's height"),
    ("[[floor]]\npx = [1, 2]\nxy_m = [nan, nan]\n", "not a number"),
    ("[[floor]]\npx = [1, 2]\n", "needs px"),
    ("[table]\nheight_m = 7\n", "between 0 and 3"),
    ("[[floor]\n", "not valid TOML"),
])
def test_bad_reference_files_say_what_to_fix(tmp_path, text, message):
    path = tmp_path / "refs.toml"
    path.write_text(text)
    with pytest.raises(UserError, match=message):
        exr.load_references(path)


# ---- poses --------------------------------------------------------------------------------------

def test_poses_meet_the_targets_with_tape_error_and_centroid_noise():
    """6 cameras, 0.2 px noise, 5 mm tape error: position <= 10 mm, orientation <= 0.1 deg."""
    scene = sp.make_scene(6, seed=2)
    refs = _refs(scene, 0.005, seed=2)
    sch, floor, table, fd, td = _dots(scene, refs, 0.2, seed=2)
    res = exs.calibrate(scene.rig, exc.assemble(scene.rig.names, fd, td, sch, floor, table),
                       floor, table)
    pos, rot = _errors(scene.rig, res.rig)
    assert max(pos.values()) < 10.0 and max(rot.values()) < 0.1
    assert res.warnings == []
    # every camera's reprojection RMS is the injected noise (2D: sqrt(2) * 0.2 px)
    for c in res.report["cameras"]:
        assert 0.8 * 0.283 < c["reprojection_rms_px"] < 1.2 * 0.283
        assert c["table_dots"] > 50 and c["floor_dots"] > 300


def test_joint_refinement_makes_cameras_agree_at_head_height():
    scene = sp.make_scene(4, seed=4)
    refs = _refs(scene, 0.005, seed=4)
    sch, floor, table, fd, td = _dots(scene, refs, 0.2, seed=4)
    dots = exc.assemble(scene.rig.names, fd, td, sch, floor, table)
    alone = exs.calibrate(scene.rig, dots, floor, table, exs.SolveOptions(joint=False))
    joint = exs.calibrate(scene.rig, dots, floor, table)
    ray_alone = sp.ray_distance_at_height(alone.rig, scene.rig, 1.7, 4.0)
    ray_joint = sp.ray_distance_at_height(joint.rig, scene.rig, 1.7, 4.0)
    assert ray_joint < 0.5 * ray_alone
    assert ray_joint < 1.0  # mm: the cameras agree to well under a marker's size


def test_misnamed_dots_are_rejected_by_ransac():
    scene = sp.make_scene(3, seed=5)
    refs = _refs(scene, 0.0, seed=5)
    sch, floor, table, fd, td = _dots(scene, refs, 0.2, seed=5, wrong_ids=0.05)
    dots = exc.assemble(scene.rig.names, fd, td, sch, floor, table)
    res = exs.calibrate(scene.rig, dots, floor, table)
    pos, rot = _errors(scene.rig, res.rig)
    assert max(pos.values()) < 10.0 and max(rot.values()) < 0.1
    # rows whose id is wrong reproject far from their dot under the true camera
    wrong = np.zeros(len(dots), bool)
    for c, name in enumerate(dots.camera_names):
        rows = dots.camera == c
        proj, _ = scene.rig[name].project(
            scene.land(sch.points_xy[dots.point[rows] % len(sch.points_xy)],
                       False)[0])
        wrong[rows] = np.linalg.norm(proj - dots.uv[rows], axis=1) > 5.0
    wrong &= dots.plane[dots.point] == exr.FLOOR
    assert wrong.sum() > 50
    assert np.mean(res.inlier[wrong]) < 0.02


def test_a_camera_that_sees_nothing_is_named_and_the_others_are_calibrated():
    scene = sp.make_scene(4, seed=6)
    blind = scene.rig[1]
    R, t = look_at(blind.centre, blind.centre + np.array([0.0, 0.0, 5.0]) +
                   np.array([0.5, 0.0, 0.0]))  # looking at the ceiling
    rig = scene.rig.replace_camera(blind.replace(rvec=rvec_from_rotation(R), t=t))
    scene = sp.ProjectorScene(rig, scene.projector, scene.table)
    refs = _refs(scene, 0.005, seed=6)
    sch, floor, table, fd, td = _dots(scene, refs, 0.2, seed=6)
    assert len(fd[1]) == 0 and len(td[1]) == 0
    res = exs.calibrate(rig, exc.assemble(rig.names, fd, td, sch, floor, table), floor, table)
    assert res.rig.names == ["cam0", "cam2", "cam3"]
    assert res.report["not_calibrated"] == ["cam1"]
    assert len(res.warnings) == 1 and "camera cam1 saw no projected dot" in res.warnings[0]
    pos, rot = _errors(rig, res.rig)
    assert max(pos.values()) < 10.0 and max(rot.values()) < 0.1


def test_too_few_dots_and_one_plane_only_are_named():
    scene = sp.make_scene(3, seed=7)
    refs = _refs(scene, 0.005, seed=7)
    sch, floor, table, fd, td = _dots(scene, refs, 0.2, seed=7)
    few = fd[0]
    fd[0] = exc.CameraDots(few.ids[:5], few.uv[:5], few.scatter_px[:5])
    td[0] = exc.CameraDots(td[0].ids[:0], td[0].uv[:0], td[0].scatter_px[:0])
    td[2] = exc.CameraDots(td[2].ids[:0], td[2].uv[:0], td[2].scatter_px[:0])
    res = exs.calibrate(scene.rig, exc.assemble(scene.rig.names, fd, td, sch, floor, table),
                       floor, table)
    assert res.report["not_calibrated"] == ["cam0"]
    text = " | ".join(res.warnings)
    assert "camera cam0 saw only 5 projected dots (needs 12)" in text
    assert "camera cam2 saw the floor dots but only 0 on the table" in text
    assert "cam1" not in text
    assert res.rig.names == ["cam1", "cam2"]


def test_no_camera_calibrated_is_an_error():
    scene = sp.make_scene(2, seed=0)
    refs = _refs(scene)
    sch, floor, table, fd, td = _dots(scene, refs)
    empty = [exc.CameraDots(d.ids[:3], d.uv[:3], d.scatter_px[:3]) for d in fd]
    dots = exc.assemble(scene.rig.names, empty, None, sch, floor, None)
    with pytest.raises(UserError) as err:
        exs.calibrate(scene.rig, dots, floor, None)
    assert str(err.value).startswith("no camera could be calibrated (cam0 saw only 3 "
                                     "projected dots, cam1 saw only 3 projected dots): "
                                     "each needs 12")


def test_floor_only_calibrates_with_one_warning():
    scene = sp.make_scene(3, table_height_m=None, seed=8)
    refs = _refs(scene, 0.005, seed=8)
    assert not refs.has_table
    sch, floor, table, fd, td = _dots(scene, refs, 0.2, seed=8)
    assert table is None and td is None
    res = exs.calibrate(scene.rig, exc.assemble(scene.rig.names, fd, None, sch, floor, None),
                       floor, None)
    assert len(res.warnings) == 1 and res.warnings[0].startswith("no table")
    pos, rot = _errors(scene.rig, res.rig)
    assert max(pos.values()) < 20.0 and max(rot.values()) < 0.2


# ---- what the wand bundle takes -----------------------------------------------------------------

def test_plane_observations_for_the_bundle_and_the_floor(tmp_path):
    from calibkit.calibrate import floor as floor_mod

    scene = sp.make_scene(4, seed=9)
    refs = _refs(scene, 0.005, seed=9)
    sch, floor, table, fd, td = _dots(scene, refs, 0.2, seed=9)
    dots = exc.assemble(scene.rig.names, fd, td, sch, floor, table)
    res = exs.calibrate(scene.rig, dots, floor, table)
    path = tmp_path / "d.npz"
    exc.save_dots(path, res.dots, res.inlier)
    back = exc.load_dots(path)
    assert len(back) == int(res.inlier.sum())
    data = exs.bundle_data(res.rig, back)
    heights = data.plane_offset_m
    # the poses used the tape's height (the dots agree with it); the file passes on the
    # best estimate of the true height, the tape and the dots weighted, for the wand
    h = res.report["table_height"]
    assert h["disagreement_sigmas"] < 3.0 and h["used_m"] == table.height_m
    assert back.plane_height_m == (0.0, h["best_m"])
    lo, hi = sorted((h["tape_m"], h["dots_m"]))
    assert lo < h["best_m"] < hi
    on_table = np.isclose(heights, h["best_m"])
    assert on_table.any() and np.all(on_table | (heights == 0.0))
    assert np.allclose(data.plane_normal, [0, 0, 1])
    assert len(data.obs_uv) == len(back) and data.xyz.shape == (len(heights), 3)
    # the sparse floor recording gives `calibkit wand --floor-kind plane` the true floor
    rec = exp.floor_recording(res.rig, res.dots, res.inlier)
    A, b = floor_mod.world_from_recording(scene.rig, rec, "plane")
    truth_floor, _ = scene.land(sch.points_xy[::7], table_present=False)
    z = floor_mod.transform_points(truth_floor, A, b)[:, 2]
    assert np.max(np.abs(z)) < 0.005
    with pytest.raises(UserError, match="not a dots file"):
        (tmp_path / "x.npz").write_text("nope")
        exc.load_dots(tmp_path / "x.npz")


# ---- rendered images, end to end ----------------------------------------------------------------

def test_rendered_capture_identifies_dots_and_places_cameras():
    """Two cameras with different latencies watch rendered projector frames: per-camera
    settling, detection and the coded identification against the truth, then poses."""
    four = sp.make_scene(4, size=(320, 240), seed=1)
    scene = sp.ProjectorScene(Rig((four.rig[0], four.rig[2])), four.projector, four.table)
    refs = _refs(scene, 0.005, seed=1)
    floor, table = exr.plane_maps(refs)
    sch = coded_schedule(PROJ, 96, 2, 10)
    tsch = exr.table_schedule(sch, table)
    # the slow camera lags the fast one by more than a pattern's sampling takes
    cfg = sp.ProjectorSimConfig(camera_latency_s=(0.02, 0.25), seed=1)
    with sp.ProjectorRigSim(scene, cfg) as dev:
        fcap = exc.capture_session(dev, sch, 2)
        dev.set_table(True)
        tcap = exc.capture_session(dev, tsch, 2, latency_frames=fcap.latency_frames)
    expected = sp.latency_frames(cfg, 2)
    assert expected[0] < expected[1]
    for c in range(2):
        assert abs(fcap.latency_frames[c] - expected[c]) <= 1
    assert fcap.frames + tcap.frames < 1800  # under 60 s at 30 fps
    for table_present, cap in ((False, fcap), (True, tcap)):
        for c, d in enumerate(cap.cameras):
            visible = sp.observe_dots(scene, sch.points_xy, table_present, 0.0)[c][0]
            shown = np.concatenate((tsch if table_present else sch).layers)
            n_visible = np.isin(visible, shown).sum()
            assert len(d) > 0.7 * n_visible
            xyz, _ = scene.land(sch.points_xy[d.ids], table_present)
            uv, _ = scene.rig[c].project(xyz)
            err = np.linalg.norm(uv - d.uv, axis=1)
            assert np.median(err) < 0.12
            assert np.mean(err > 1.0) < 0.01  # misnamed or damaged dots: rare
    dots = exc.assemble(scene.rig.names, fcap.cameras, tcap.cameras, sch, floor, table)
    res = exs.calibrate(scene.rig, dots, floor, table)
    pos, rot = _errors(scene.rig, res.rig)
    assert max(pos.values()) < 15.0 and max(rot.values()) < 0.15


def test_example_reference_file_matches_the_simulator():
    """fixtures/extrinsic_refs.toml holds the simulator's (seed 0) tape measurements."""
    from pathlib import Path

    refs = exr.load_references(Path(__file__).parent.parent / "fixtures" / "extrinsic_refs.toml")
    scene = sp.make_scene(6, seed=0)
    truth, plane = scene.land(refs.floor_px, table_present=False)
    assert np.all(plane == 0)
    err = refs.floor_xy_m - truth[:, :2]
    assert np.sqrt(np.mean(err**2)) < 0.008  # 5 mm per axis, written to the millimetre
    floor, table = exr.plane_maps(refs)
    assert table is not None and table.height_m == scene.table.height_m


def test_plane_dots_hold_the_world_frame_in_a_wand_bundle():
    """The dots joined to a wand solve (bundle_data + join_bundle_data): no world transform
    afterwards, yet the cameras stay in the tape's frame, and agree better at head height."""
    from calibkit.calibrate import bundle
    from calibkit.calibrate.wand_solve import labelled_wand_data
    from calibkit.synthetic import sim

    scene = sp.make_scene(4, seed=3)
    refs = _refs(scene, 0.005, seed=3)
    sch, floor, table, fd, td = _dots(scene, refs, 0.2, seed=3)
    res = exs.calibrate(scene.rig, exc.assemble(scene.rig.names, fd, td, sch, floor, table),
                       floor, table)
    spacing = (0.0, 0.2, 0.5)
    obs = sim.observe(scene.rig, sim.wand_motion(200, 100.0, 4.0, spacing, seed=3),
                      noise_px=0.2, seed=3)
    wand = labelled_wand_data(res.rig, obs, spacing)
    joined = exs.join_bundle_data(wand, exs.bundle_data(res.rig, res.dots.select(res.inlier)))
    assert len(joined.xyz) == len(wand.xyz) + len(np.unique(res.dots.point[res.inlier]))
    out = bundle.solve(joined, bundle.BundleOptions(known_sigma_m=0.005, plane_sigma_m=0.002,
                                                    noise_px=0.3))
    pos, rot = _errors(scene.rig, out.rig)
    assert max(pos.values()) < 10.0 and max(rot.values()) < 0.1
    assert (sp.ray_distance_at_height(out.rig, scene.rig, 1.7, 4.0)
            < sp.ray_distance_at_height(res.rig, scene.rig, 1.7, 4.0))


def test_table_left_in_for_the_floor_session_is_rejected_as_outliers():
    """Dots that land on a table left under the projector are mapped as floor points, 0.75 m
    off: RANSAC and the inlier pass drop them, and the poses still meet the targets."""
    scene = sp.make_scene(4, seed=10)
    refs = _refs(scene, 0.005, seed=10)
    sch = coded_schedule(PROJ, 64, 2, 8)
    floor, table = exr.plane_maps(refs)
    tsch = exr.table_schedule(sch, table)
    fd = sp.simulated_dots(scene, sch.points_xy, True, 0.2, seed=10)  # table in the light
    td = sp.simulated_dots(scene, sch.points_xy, True, 0.2, seed=11,
                           shown=np.concatenate(tsch.layers))
    dots = exc.assemble(scene.rig.names, fd, td, sch, floor, table)
    res = exs.calibrate(scene.rig, dots, floor, table)
    n = len(sch.points_xy)
    floor_rows = dots.point < n
    _, landed = scene.land(sch.points_xy[dots.point[floor_rows] % n], table_present=True)
    on_table = np.zeros(len(dots), bool)
    on_table[np.flatnonzero(floor_rows)[landed == 1]] = True
    assert on_table.sum() > 200
    assert np.mean(res.inlier[on_table]) < 0.05
    pos, rot = _errors(scene.rig, res.rig)
    assert max(pos.values()) < 10.0 and max(rot.values()) < 0.1


# ---- the table's height: the tape's error, and the dots' own measure ---------------------------

def test_the_sim_tape_measures_the_table_height_with_its_error(tmp_path):
    """`extrinsic --sim` hands the estimate the tape's height, not the truth: off by a seeded
    draw whose spread over seeds is the stated TAPE_HEIGHT_ERROR_MM."""
    from calibkit.synthetic import extrinsic_sim, sim

    sim.make_rig(3, 4.0, seed=0).save(tmp_path / "intr.toml")  # only the names and sizes

    def tape_error_mm(seed: int) -> float:
        run = extrinsic_sim.setup(tmp_path / "intr.toml", None, 3, None, 4.0, 0.75, 5.0,
                                  PROJ, seed)
        return 1000.0 * (run.refs.table_height_m - run.scene.table.height_m)

    errors = np.array([tape_error_mm(s) for s in range(40)])
    assert tape_error_mm(3) == errors[3]  # seeded
    assert np.all(errors != 0.0) and len(np.unique(errors)) == len(errors)
    # 40 draws: the sample SD within 25 % of the stated one (chi-square, ~4 sigma)
    sd = float(np.sqrt(np.mean(errors**2)))
    assert 0.75 * TAPE_HEIGHT_ERROR_MM < sd < 1.25 * TAPE_HEIGHT_ERROR_MM


def test_the_dots_recover_the_table_height_from_a_bad_tape():
    """The tape reads the table 10 mm high (five times its stated error): the dots measure
    the height, the solve uses mostly theirs and says so; held at the tape's height instead,
    every camera is pulled off by the false scale."""
    scene = sp.make_scene(6, seed=2)
    good = _refs(scene, 0.005, seed=2, height_error_m=0.0)
    true_m = scene.table.height_m
    bad = exr.References(good.floor_px, good.floor_xy_m, good.table_px, good.table_xy_m,
                         true_m + 0.010)
    sch, floor, table, fd, td = _dots(scene, bad, 0.2, seed=2)
    dots = exc.assemble(scene.rig.names, fd, td, sch, floor, table)
    res = exs.calibrate(scene.rig, dots, floor, table)
    h = res.report["table_height"]
    assert abs(h["tape_m"] - (true_m + 0.010)) < 1e-12
    # the dots' figure: within the floor map's scale error (5 mm tape over the references'
    # spread, about 1 mm at 0.75 m) of the truth, and the height used close to it
    assert abs(h["dots_m"] - true_m) < 3e-3 and 0.3 < h["dots_sigma_mm"] < 2.0
    assert abs(h["used_m"] - true_m) < 3e-3 and h["used_m"] == h["best_m"]
    assert h["disagreement_sigmas"] > 3.0
    assert any("re-measure the table's height" in w for w in res.warnings), res.warnings
    pos, rot = _errors(scene.rig, res.rig)
    assert max(pos.values()) < 10.0 and max(rot.values()) < 0.1
    held = exs.calibrate(scene.rig, dots, floor, table, exs.SolveOptions(refine_height=False))
    assert held.report["table_height"] is None
    pos_held, _ = _errors(scene.rig, held.rig)
    assert max(pos_held.values()) > 1.5 * max(pos.values())
    assert sp.ray_distance_at_height(res.rig, scene.rig, 1.7, 4.0) < \
        sp.ray_distance_at_height(held.rig, scene.rig, 1.7, 4.0)
