"""`calibkit extrinsic --projector` end to end on the simulator, and its error messages."""

from __future__ import annotations

import json

import numpy as np

from calibkit.calibrate.compare import compare_rigs
from calibkit.calibrate.extrinsic_capture import load_dots
from calibkit.calibrate.extrinsic_reference import load_references
from calibkit.core.camera import Rig
from calibkit.core.recording import load_observations


def dots_height_m(path) -> float:
    return load_dots(path).plane_height_m[1]


def _one_line_error(res, code=2):
    assert res.code == code, res.out + res.err
    lines = [line for line in res.err.strip().splitlines() if line]
    assert len(lines) == 1 and lines[0].startswith("calibkit: error: "), res.err
    assert "Traceback" not in res.err
    return lines[0]


def _intrinsics(calibkit_cli, tmp_path, cameras: int, seed: int, *extra):
    """The chain's first step: every camera of the simulated rig (made from --cameras and
    --seed) estimated from monitor views, into intr.toml."""
    intr = tmp_path / "intr.toml"
    r = calibkit_cli("intrinsic", "--sim", "--camera", "all", "--no-render", "--cameras",
                     cameras, "--seed", seed, "--views", 4, "--step", 120, "--rig", intr,
                     *extra)
    assert r.code == 0, r.err
    return intr


def test_sim_writes_the_rig_truth_and_plane_observations(calibkit_cli, tmp_path):
    out = tmp_path / "rig.toml"
    intr = _intrinsics(calibkit_cli, tmp_path, 4, 3)
    res = calibkit_cli("extrinsic", "--projector", "--sim", "--intrinsics", intr, "--seed",
                       "3", "--out", out, "--json", tmp_path / "r.json")
    assert res.code == 0, res.err
    rig, truth = Rig.load(out), Rig.load(tmp_path / "rig.truth.toml")
    assert rig.names == truth.names == ["cam0", "cam1", "cam2", "cam3"]
    # the intrinsics are the file's estimate, passed on with their uncertainty
    est = Rig.load(intr)
    for cam, e, t in zip(rig, est, truth, strict=True):
        assert cam.fx == e.fx and cam.cx == e.cx and cam.fx != t.fx
        assert rig.quality["intrinsic"][cam.name]["std"] == est.quality["intrinsic"][
            cam.name]["std"]
    cmp = compare_rigs(truth, rig, align=False)
    assert max(c["position_mm"] for c in cmp["cameras"]) < 10.0
    assert max(c["rotation_deg"] for c in cmp["cameras"]) < 0.1
    report = json.loads((tmp_path / "r.json").read_text())
    assert report["truth"]["position_error_max_mm"] < 10.0
    assert report["capture"]["seconds_at_30fps"] < 60.0
    for cam in report["cameras"]:
        assert cam["calibrated"] and cam["table_dots"] > 20
        assert 0.2 < cam["reprojection_rms_px"] < 0.35  # 0.2 px per axis injected
        assert 0 < cam["mean_ray_distance_table_mm"] < 5
    assert rig.quality["extrinsic"]["reprojection_rms_px"] > 0
    # the simulated tape measurements read back as a reference file
    refs = load_references(tmp_path / "rig.refs.toml")
    assert len(refs.floor_px) == 16
    # the tape's height is not the truth: off by a seeded draw of its stated error, which
    # only the truth figures know; the solve's height comes from the tape and the dots
    th = report["truth"]["table_height"]
    assert th["true_m"] == 0.75 and refs.table_height_m != 0.75
    # (the file holds it to 0.1 mm, as a tape is read)
    assert abs(th["tape_error_mm"] - 1000 * (refs.table_height_m - 0.75)) <= 0.05
    assert abs(report["table_height"]["tape_m"] - refs.table_height_m) <= 0.05e-3
    assert abs(th["used_error_mm"]) < 4.0 and "scale_error_ppm" in report["truth"]
    assert dots_height_m(tmp_path / "rig.dots.npz") == report["table_height"]["best_m"]
    dots = load_dots(tmp_path / "rig.dots.npz")
    assert set(dots.camera_names) == set(rig.names) and len(dots) > 1000
    floor_obs, _ = load_observations(tmp_path / "rig.floor.mcrec", rig)
    assert len(floor_obs.frames()) == 3
    # calibkit compare reads the pair as written
    cmp_res = calibkit_cli("compare", tmp_path / "rig.truth.toml", out, "--no-align")
    assert cmp_res.code == 0 and "cam3" in cmp_res.out


def test_sim_without_a_table_warns_and_still_calibrates(calibkit_cli, tmp_path):
    out = tmp_path / "rig.toml"
    intr = _intrinsics(calibkit_cli, tmp_path, 3, 0)
    res = calibkit_cli("extrinsic", "--projector", "--sim", "--intrinsics", intr,
                       "--table-height", "0", "--no-joint", "--out", out)
    assert res.code == 0, res.err
    assert "warning: no table" in res.err
    assert len(Rig.load(out)) == 3


def test_rendered_sim_runs_detection_end_to_end(calibkit_cli, tmp_path):
    out = tmp_path / "rig.toml"
    intr = _intrinsics(calibkit_cli, tmp_path, 2, 1, "--size", "320x240")
    res = calibkit_cli("extrinsic", "--projector", "--sim", "--render", "--intrinsics", intr,
                       "--size", "320x240", "--step", "80", "--shifts", "1", "--radius", "10",
                       "--seed", "1", "--table-height", "0", "--out", out,
                       "--json", tmp_path / "r.json")
    assert res.code == 0, res.err
    report = json.loads((tmp_path / "r.json").read_text())
    assert report["capture"]["simulated_frames"] is False
    assert 0 < report["capture"]["seconds_at_30fps"] < 30
    assert "floor dots:" in res.err  # progress on stderr
    # floor only, one grid layer (the table session is tested in test_extrinsic)
    assert report["truth"]["position_error_max_mm"] < 25.0
    assert report["truth"]["rotation_error_max_deg"] < 0.25
    assert all(c["floor_dots"] > 60 for c in report["cameras"])


def test_template_then_unmeasured_file_is_refused(calibkit_cli, tmp_path):
    tpl = tmp_path / "refs.toml"
    res = calibkit_cli("extrinsic", "--projector", "--template", tpl,
                       "--projector-size", "1920x1080")
    assert res.code == 0, res.err
    text = tpl.read_text()
    assert text.count("[[floor]]") == 16 and "size = [1920, 1080]" in text
    rig = tmp_path / "intr.toml"
    from calibkit.synthetic import sim

    sim.make_rig(2).save(rig)
    res = calibkit_cli("extrinsic", "--projector", "--refs", tpl, "--intrinsics", rig,
                       "--out", tmp_path / "out.toml", "--camera", "0", "--camera", "1")
    line = _one_line_error(res)
    assert "floor point 1 holds a value that is not a number" in line


def test_usage_errors_are_one_line(calibkit_cli, tmp_path):
    line = _one_line_error(calibkit_cli("extrinsic", "--sim", "--out", tmp_path / "x.toml"))
    assert "--projector" in line
    line = _one_line_error(calibkit_cli("extrinsic", "--projector", "--out",
                                        tmp_path / "x.toml"))
    assert "--refs REFS.toml is required" in line
    refs = tmp_path / "refs.toml"
    pts = ((0, 0), (500, 0), (0, 500), (500, 500))
    refs.write_text("".join(f"[[floor]]\npx = [{u}, {v}]\nxy_m = [{u / 100}, {v / 100}]\n"
                            for u, v in pts)
                    + "".join(f"[[table.point]]\npx = [{u}, {v}]\nxy_m = [{u / 900}, "
                              f"{v / 900}]\n" for u, v in pts))
    line = _one_line_error(calibkit_cli("extrinsic", "--projector", "--refs", refs,
                                        "--intrinsics", refs, "--out", tmp_path / "x.toml"))
    assert "table points are given but not the table's height" in line
    line = _one_line_error(calibkit_cli("extrinsic", "--projector", "--sim", "--out",
                                        tmp_path / "x.toml", "--table-height", "-1"))
    assert "--table-height" in line
    assert not (tmp_path / "x.toml").exists()


def test_refs_without_table_reject_table_flag(calibkit_cli, tmp_path):
    refs = tmp_path / "refs.toml"
    pts = ((0, 0), (500, 0), (0, 500), (500, 500), (250, 250))
    refs.write_text("".join(f"[[floor]]\npx = [{u}, {v}]\nxy_m = [{u / 100}, "
                            f"{v / 100 + 0.001 * np.sin(u)}]\n" for u, v in pts))
    from calibkit.synthetic import sim

    sim.make_rig(2).save(tmp_path / "intr.toml")
    line = _one_line_error(calibkit_cli("extrinsic", "--projector", "--refs", refs,
                                        "--intrinsics", tmp_path / "intr.toml", "--table",
                                        "--out", tmp_path / "x.toml"))
    assert "--table needs the table" in line
    line = _one_line_error(calibkit_cli("extrinsic", "--projector", "--refs", refs,
                                        "--intrinsics", tmp_path / "intr.toml",
                                        "--out", tmp_path / "x.toml"))
    assert "--camera" in line


def test_intrinsics_without_the_cameras_are_refused(calibkit_cli, tmp_path):
    from calibkit.synthetic import sim

    rig = sim.make_rig(2)
    Rig(tuple(c.replace(name=f"other{i}") for i, c in enumerate(rig))).save(tmp_path / "i.toml")
    line = _one_line_error(calibkit_cli("extrinsic", "--projector", "--sim", "--cameras", "2",
                                        "--intrinsics", tmp_path / "i.toml",
                                        "--out", tmp_path / "x.toml"))
    assert "camera 'cam0' of the simulated rig has no intrinsics in --intrinsics" in line
    assert "(it has other0, other1)" in line and "--sim-rig" in line
    # a file of another size of camera
    Rig(tuple(c.replace(size=(320, 240)) for c in rig)).save(tmp_path / "s.toml")
    line = _one_line_error(calibkit_cli("extrinsic", "--projector", "--sim", "--intrinsics",
                                        tmp_path / "s.toml", "--out", tmp_path / "x.toml"))
    assert "is 320x240 in --intrinsics" in line and "640x480 in the simulated rig" in line
    # no intrinsics at all: the truth is never the start
    line = _one_line_error(calibkit_cli("extrinsic", "--projector", "--sim",
                                        "--out", tmp_path / "x.toml"))
    assert "run `calibkit intrinsic --sim --camera all" in line
    assert not (tmp_path / "x.toml").exists()


def test_sim_starts_from_the_intrinsics_file(calibkit_cli, tmp_path):
    """A file 1 % off in focal length: the poses come out that far off the truth (the
    cameras pulled along their axes), which they would not if the truth were used."""
    world = tmp_path / "world.truth.toml"
    from calibkit.synthetic import sim

    truth = sim.make_rig(3, 4.0, seed=2)
    truth.save(world)
    intr = _intrinsics(calibkit_cli, tmp_path, 3, 2)  # the same rig: --cameras 3 --seed 2
    good = Rig.load(intr)
    bad = Rig(tuple(c.replace(fx=c.fx * 1.01, fy=c.fy * 1.01) for c in good))
    bad.save(tmp_path / "bad.toml")
    err = {}
    for name, path in (("good", intr), ("bad", tmp_path / "bad.toml")):
        out = tmp_path / f"{name}.toml"
        res = calibkit_cli("extrinsic", "--projector", "--sim", "--sim-rig", world,
                           "--intrinsics", path, "--seed", 2, "--out", out)
        assert res.code == 0, res.err
        rig = Rig.load(out)
        assert [c.fx for c in rig] == [c.fx for c in Rig.load(path)]
        err[name] = max(c["position_mm"] for c in compare_rigs(truth, rig, align=False)[
            "cameras"])
    # ~3.5 m from the floor's middle, 1 % of focal length moves a camera by ~35 mm
    assert err["good"] < 10.0 and err["bad"] > 15.0


def test_live_path_with_a_stand_in_projector_and_cameras(calibkit_cli, tmp_path, monkeypatch):
    """The live code path (--camera, --monitor) end to end: the projector window and the
    camera devices are stood in for by the simulator (no display or camera here)."""
    import calibkit.cameras
    import projector.display
    import projector.screens
    from calibkit.calibrate import extrinsic_reference as exr
    from calibkit.cameras import Frame
    from calibkit.synthetic import projector as sp

    four = sp.make_scene(4, size=(320, 240), table_height_m=None, seed=2)
    scene = sp.ProjectorScene(Rig((four.rig[0], four.rig[2])), four.projector, None)
    m = sp.measured_references(scene, exr.reference_layout_px((1280, 800)), np.zeros((0, 2)),
                               0.005, seed=2)
    (tmp_path / "refs.toml").write_text(exr.references_toml(
        exr.References(m["floor_px"], m["floor_xy_m"])))
    scene.rig.save(tmp_path / "intr.toml")
    rig_sim = sp.ProjectorRigSim(scene, sp.ProjectorSimConfig(camera_latency_s=(0.03, 0.1)))
    latest: dict[int, np.ndarray] = {}

    class Window:
        def __init__(self, monitor):
            assert monitor == 2

        def show(self, dots):
            rig_sim.show(dots)

        def close(self):
            rig_sim.close()

    class Camera:
        def __init__(self, c):
            self.c = c

        def __iter__(self):
            k = 0
            while True:
                if self.c == 0:  # both cameras expose together: one grab serves both
                    latest.update(enumerate(rig_sim.grab()))
                yield Frame(f"cam{self.c}", k, k, latest[self.c])
                k += 1

        def close(self):
            pass

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            self.close()

    monkeypatch.setattr(projector.display, "WindowDisplay", Window)
    monkeypatch.setattr(projector.screens, "require_display", lambda: None)
    monkeypatch.setattr(calibkit.cameras, "open_camera",
                        lambda spec, name=None: Camera(int(spec)))
    out = tmp_path / "rig.toml"
    res = calibkit_cli("extrinsic", "--projector", "--refs", tmp_path / "refs.toml",
                       "--intrinsics", tmp_path / "intr.toml", "--camera", "0", "--camera",
                       "1", "--monitor", "2", "--step", "96", "--radius", "10", "--out", out)
    assert res.code == 0, res.err
    assert "warning: no table" in res.err
    cmp = compare_rigs(scene.rig, Rig.load(out), align=False)
    assert max(c["position_mm"] for c in cmp["cameras"]) < 25.0
    assert max(c["rotation_deg"] for c in cmp["cameras"]) < 0.25


def test_show_refs_lights_the_reference_dots(calibkit_cli, tmp_path, monkeypatch):
    import builtins

    import projector.display
    import projector.screens

    shown = []

    class Window:
        def __init__(self, monitor):
            self.monitor = monitor

        def show(self, dots):
            shown.append((self.monitor, dots))

        def close(self):
            shown.append("closed")

    monkeypatch.setattr(projector.display, "WindowDisplay", Window)
    monkeypatch.setattr(projector.screens, "require_display", lambda: None)
    monkeypatch.setattr(builtins, "input", lambda prompt="": "")
    from pathlib import Path

    refs = Path(__file__).parent.parent / "fixtures" / "extrinsic_refs.toml"
    res = calibkit_cli("extrinsic", "--projector", "--show-refs", "--refs", refs,
                       "--monitor", "1", "--radius", "12")
    assert res.code == 0, res.err
    (monitor, dots), closed = shown
    assert monitor == 1 and closed == "closed"
    assert len(dots.xy) == 16 + 5 and np.all(dots.radius_px == 12)
    assert np.allclose(dots.xy[0], [128, 80])
    line = _one_line_error(calibkit_cli("extrinsic", "--projector", "--show-refs", "--sim"))
    assert "not with --sim" in line
