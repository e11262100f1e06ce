"""`calibkit wand` and `calibkit floor` from the command line, against the simulator's truth."""

from __future__ import annotations

import json

import numpy as np
import pytest

from calibkit.core.camera import Rig
from calibkit.core.pairing import pair_frames
from calibkit.core.recording import load_observations, save_observations
from calibkit.synthetic import sim


def _one_line_error(result) -> None:
    assert result.code == 2
    assert "Traceback" not in result.err
    assert len(result.err.strip().splitlines()) == 1 and "error:" in result.err


def _chain_start(calibkit_cli, tmp_path, cameras: int, seed: int):
    """The first step of the chain a user runs on the simulator: a true rig (the hardware)
    and its cameras' intrinsics estimated from simulated monitor views."""
    world, intr = tmp_path / "world.truth.toml", tmp_path / "intr.toml"
    assert calibkit_cli("sim", "rig", "--cameras", cameras, "--seed", seed, "--out",
                        world).code == 0
    r = calibkit_cli("intrinsic", "--sim", "--sim-rig", world, "--camera", "all",
                     "--no-render", "--views", 4, "--step", 120, "--seed", seed, "--rig", intr)
    assert r.code == 0, r.err
    return world, intr


def test_wand_sim_end_to_end(calibkit_cli, tmp_path):
    world, intr = _chain_start(calibkit_cli, tmp_path, 4, 3)
    out = tmp_path / "rig.toml"
    r = calibkit_cli("wand", "--sim", "--sim-rig", world, "--intrinsics", intr, "--out", out,
                     "--frames", "400", "--noise-px", "0.1", "--min-samples", "150",
                     "--min-coverage", "0.1", "--json", tmp_path / "w.json", "--seed", "3")
    assert r.code == 0, r.err
    for name in ("rig.toml", "rig.truth.toml", "rig.capture.mcrec", "rig.layout.png",
                 "rig.residuals.png", "w.json"):
        assert (tmp_path / name).stat().st_size > 0, name
    report = json.loads((tmp_path / "w.json").read_text())
    assert report["solve"]["refine_intrinsics"] is True  # the default
    # with the monitor's own views in the graph (the intrinsic step's NAME.views.npz, found
    # from the rig file), fitted at the monitor's noise: 0.035 px per axis
    assert "monitor dots in 16 views" in r.out
    for row in report["intrinsics"]["cameras"]:
        assert row["prior_from"] == "intrinsic step's views", row
        assert 0.025 < row["views_rms_px"] < 0.045 and row["views_points"] > 100
    # the capture stopped by itself once every camera had 150 sightings
    captured, _ = load_observations(tmp_path / "rig.capture.mcrec")
    assert len(captured.frames()) < 400
    # (the recording keeps each camera's own counter; the solve's frames are wand frames)
    paired = pair_frames(captured).obs
    assert report["held_out"]["frames"] + report["solve"]["frames"] <= len(paired.frames())
    # 0.1 px noise: ~0.14 px per 2D residual, less what triangulation absorbs
    assert 0.08 < report["held_out"]["reprojection_rms_px"] < 0.16
    assert report["grade"] in ("excellent", "good") and report["checks"]["ok"]
    assert report["world_frame"] == "floor"
    # the truth written beside the result is the hardware it was given, and only that
    est, true = Rig.load(out), Rig.load(tmp_path / "rig.truth.toml")
    np.testing.assert_allclose(true.centres(), Rig.load(world).centres())
    assert [c.fx for c in true] == [c.fx for c in Rig.load(world)]
    # the intrinsics were refined from the monitor's estimate, never set to the truth
    assert all(e.fx != t.fx and e.cx != t.cx for e, t in zip(est, true, strict=True))
    assert f"grade: {report['grade']}" in r.out


def test_wand_sim_starts_from_the_intrinsics_file(calibkit_cli, tmp_path):
    """The intrinsics come from the file, not the simulator: kept fixed, the monitor's
    estimate gives a rig close to the truth, and the same file 1 % off in focal length and
    4 px in the principal point gives a rig that far off, against a truth it never read."""
    world, intr = _chain_start(calibkit_cli, tmp_path, 4, 11)
    good = Rig.load(intr)
    bad = Rig(tuple(c.replace(fx=c.fx * 1.01, fy=c.fy * 1.01, cx=c.cx + 4.0) for c in good),
              good.quality)
    bad.save(tmp_path / "bad.toml")
    runs = {}
    for name, path in (("bad", tmp_path / "bad.toml"), ("good", intr)):
        out = tmp_path / f"{name}.toml"
        r = calibkit_cli("wand", "--sim", "--sim-rig", world, "--intrinsics", path,
                         "--fix-intrinsics", "--frames", 400, "--min-samples", 150,
                         "--min-coverage", 0.1, "--seed", 11, "--no-plots", "--out", out,
                         "--json", tmp_path / f"{name}.json")
        assert r.code == 0, r.err
        runs[name] = Rig.load(out)
        assert json.loads((tmp_path / f"{name}.json").read_text())["solve"][
            "refine_intrinsics"] is False
    truth = Rig.load(world)
    for rig, given in ((runs["bad"], bad), (runs["good"], good)):
        for e, g in zip(rig, given, strict=True):
            assert e.fx == pytest.approx(g.fx) and e.cx == pytest.approx(g.cx)
    # the simulated L-frame lies at the true origin: compared as they stand; 0.1 px noise
    # and the monitor's 0.01 % / 0.04 px leave ~1-2 mm, a few from the L-frame's tilt
    err = np.linalg.norm(runs["good"].centres() - truth.centres(), axis=1)
    assert err.max() < 6e-3
    from calibkit.calibrate.compare import compare_rigs

    grid_bad = compare_rigs(truth, runs["bad"])["grid_rms_mm"]
    grid_good = compare_rigs(truth, runs["good"])["grid_rms_mm"]
    assert grid_bad > 5 * grid_good  # the file's error went into the rig


def test_wand_sim_without_intrinsics_says_what_to_run(calibkit_cli, tmp_path):
    r = calibkit_cli("wand", "--sim", "--out", tmp_path / "out.toml")
    _one_line_error(r)
    assert "calibkit intrinsic --sim" in r.err and "--intrinsics" in r.err
    assert not (tmp_path / "out.toml").exists()


def test_wand_from_csv_with_intrinsics(calibkit_cli, tmp_path):
    rig_file, csv = tmp_path / "true.toml", tmp_path / "wand.csv"
    assert calibkit_cli("sim", "rig", "--out", rig_file, "--cameras", "4", "--seed",
                        "4").code == 0
    assert calibkit_cli("sim", "wand", "--rig", rig_file, "--out", csv, "--frames", "300",
                        "--noise-px", "0.2", "--ghosts", "0.3", "--seed", "4").code == 0
    # the file holds the exact intrinsics: kept as they are, the poses alone are tested
    r = calibkit_cli("wand", "--from", csv, "--intrinsics", rig_file, "--fix-intrinsics",
                     "--out", tmp_path / "out.toml", "--json", tmp_path / "w.json",
                     "--no-plots")
    assert r.code == 0, r.err
    report = json.loads((tmp_path / "w.json").read_text())
    assert report["world_frame"].startswith("cameras")  # no floor given: provisional
    assert report["held_out"]["reprojection_rms_px"] < 0.3
    est, true = Rig.load(tmp_path / "out.toml"), Rig.load(rig_file)
    from calibkit.core.geometry import rigid_fit

    R, t, s = rigid_fit(est.centres(), true.centres(), scale=True)
    assert abs(s - 1) < 2e-3  # the wand's length sets the scale
    assert np.max(np.linalg.norm(est.centres() @ R.T + t - true.centres(), axis=1)) < 5e-3
    assert not (tmp_path / "out.layout.png").exists()


def test_a_camera_that_never_sees_the_wand(calibkit_cli, tmp_path):
    rig = sim.make_rig(5, 4.0, seed=5)
    rig.save(tmp_path / "rig.toml")
    truth = sim.wand_motion(300, 100.0, 4.0, (0.0, 0.2, 0.5), seed=5)
    obs = sim.observe(rig, truth, noise_px=0.2, seed=5)
    save_observations(tmp_path / "w.mcrec", obs.select(obs.camera != 2))
    r = calibkit_cli("wand", "--from", tmp_path / "w.mcrec", "--intrinsics",
                     tmp_path / "rig.toml", "--out", tmp_path / "out.toml", "--json",
                     tmp_path / "w.json", "--no-plots")
    assert r.code == 0, r.err
    assert "warning: camera cam2 saw the wand in 0 frames" in r.out
    report = json.loads((tmp_path / "w.json").read_text())
    assert report["left_out_cameras"] == ["cam2"]
    assert Rig.load(tmp_path / "out.toml").names == ["cam0", "cam1", "cam3", "cam4"]
    assert report["held_out"]["reprojection_rms_px"] < 0.35


def test_wand_with_initial_poses_and_intrinsics_refined(calibkit_cli, tmp_path):
    rig = sim.make_rig(4, 4.0, seed=6)
    rig.save(tmp_path / "rig.toml")
    truth = sim.wand_motion(300, 100.0, 4.0, (0.0, 0.2, 0.5), seed=6)
    save_observations(tmp_path / "w.mcrec", sim.observe(rig, truth, noise_px=0.2, seed=6))
    r = calibkit_cli("wand", "--from", tmp_path / "w.mcrec", "--rig", tmp_path / "rig.toml",
                     "--refine-intrinsics", "--out", tmp_path / "out.toml", "--json",
                     tmp_path / "w.json", "--no-plots")
    assert r.code == 0, r.err
    report = json.loads((tmp_path / "w.json").read_text())
    assert report["solve"]["refine_intrinsics"] is True
    assert report["held_out"]["reprojection_rms_px"] < 0.3
    out = Rig.load(tmp_path / "out.toml")
    assert all(abs(a.fx / b.fx - 1) < 0.005 for a, b in zip(out, rig, strict=True))


@pytest.mark.parametrize("args", [
    [],  # no source
    ["--sim"],  # no intrinsics: never the truth
    ["--sim", "--intrinsics", "rig.toml", "--cameras", "5"],  # not this rig's cameras
    ["--sim", "--intrinsics", "rig.toml", "--sim-rig", "missing.toml"],
    ["--sim", "--from", "x.mcrec"],
    ["--from", "missing.mcrec", "--intrinsics", "rig.toml"],
    ["--from", "w.mcrec"],  # no intrinsics
    ["--sim", "--spacing", "0,0.25,0.5"],  # equal spacings
    ["--sim", "--spacing", "0,a"],
    ["--sim", "--holdout", "1.5"],
    ["--from", "w.mcrec", "--intrinsics", "other.toml"],  # a camera with no intrinsics
])
def test_wand_bad_input_is_one_clear_line(calibkit_cli, tmp_path, monkeypatch, args):
    monkeypatch.chdir(tmp_path)
    rig = sim.make_rig(3, 4.0, seed=1)
    rig.save(tmp_path / "rig.toml")
    Rig(rig.cameras[:2]).save(tmp_path / "other.toml")
    truth = sim.wand_motion(20, 100.0, 4.0, (0.0, 0.2, 0.5), seed=1)
    save_observations(tmp_path / "w.mcrec", sim.observe(rig, truth, seed=1))
    _one_line_error(calibkit_cli("wand", "--out", "out.toml", *args))
    assert not (tmp_path / "out.toml").exists()


def test_floor_sim_and_errors(calibkit_cli, tmp_path):
    r = calibkit_cli("floor", "--sim", "--out", tmp_path / "f.toml", "--json",
                     tmp_path / "f.json")
    assert r.code == 0, r.err
    figures = json.loads((tmp_path / "f.json").read_text())
    # 0.1 px on 30 frames of an L-frame: the frame tilts well under a milliradian
    assert max(figures["centre_error_mm"]) < 5.0
    _one_line_error(calibkit_cli("floor", "--out", tmp_path / "g.toml"))
    _one_line_error(calibkit_cli("floor", "--sim", "--out", tmp_path / "g.toml", "--long",
                                 "0.3", "--short", "0.3"))
    # a recording with no L-frame in it
    rig = Rig.load(tmp_path / "f.truth.toml")
    truth = sim.static_markers(2, 10, 4.0, seed=2)
    save_observations(tmp_path / "s.mcrec", sim.observe(rig, truth, noise_px=0.1, seed=2))
    bad = calibkit_cli("floor", "--rig", tmp_path / "f.truth.toml", "--from",
                       tmp_path / "s.mcrec", "--out", tmp_path / "g.toml")
    _one_line_error(bad)
    assert "no L-frame" in bad.err


def test_live_capture_from_camera_image_folders(calibkit_cli, tmp_path):
    """The live path (frame sources, detection, the capture loop) on rendered frames: one
    folder of images per camera stands in for a camera device."""
    import cv2

    rig = sim.make_rig(3, 4.0, seed=7)
    rig.save(tmp_path / "rig.toml")
    truth = sim.wand_motion(60, 100.0, 4.0, (0.0, 0.2, 0.5), seed=7)
    folders = []
    for cam in rig:
        folder = tmp_path / cam.name
        folder.mkdir()
        for f in range(60):
            _, xyz = truth.at_frame(f)
            image, _, _ = sim.render_frame(cam, xyz, seed=f)
            cv2.imwrite(str(folder / f"{f:03d}.png"), image)
        folders.append(folder)
    args = ["wand", "--intrinsics", tmp_path / "rig.toml", "--out", tmp_path / "out.toml",
            "--json", tmp_path / "w.json", "--no-plots", "--holdout", "0"]
    for folder in folders:
        args += ["--camera", folder]
    r = calibkit_cli(*args)
    assert r.code == 0, r.err
    captured, _ = load_observations(tmp_path / "out.capture.mcrec")
    assert len(captured.frames()) == 60  # every frame of every camera went through
    report = json.loads((tmp_path / "w.json").read_text())
    seen = report["identification"]["frames_with_wand"]
    assert all(n > 40 for n in seen.values()), seen
    # rendered spots detected to a few hundredths of a pixel: a tight fit
    assert report["solve"]["reprojection_rms_px"] < 0.3


def test_wand_with_an_lframe_recording_sets_the_floor(calibkit_cli, tmp_path):
    from calibkit.calibrate import floor
    from calibkit.core.observations import Truth

    rig = sim.make_rig(4, 4.0, seed=8)
    rig.save(tmp_path / "rig.toml")
    truth = sim.wand_motion(300, 100.0, 4.0, (0.0, 0.2, 0.5), seed=8)
    save_observations(tmp_path / "w.mcrec", sim.observe(rig, truth, noise_px=0.1, seed=8))
    pts = floor.LFrame().points((0.0, 0.0), 0.0)
    lf = Truth(np.repeat(np.arange(30), 3), np.tile(np.arange(3), 30), np.tile(pts, (30, 1)))
    save_observations(tmp_path / "l.mcrec", sim.observe(rig, lf, noise_px=0.1, seed=9))
    r = calibkit_cli("wand", "--from", tmp_path / "w.mcrec", "--intrinsics",
                     tmp_path / "rig.toml", "--fix-intrinsics", "--floor", tmp_path / "l.mcrec",
                     "--out", tmp_path / "out.toml", "--no-plots")
    assert r.code == 0, r.err
    assert "world frame: floor" in r.out
    # the L-frame lies at the true origin: the result is in the true frame, no alignment
    err = np.linalg.norm(Rig.load(tmp_path / "out.toml").centres() - rig.centres(), axis=1)
    assert err.max() < 6e-3
