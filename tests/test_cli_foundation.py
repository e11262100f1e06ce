"""The foundation's command lines as a user runs them: sim, rig, compare, convert, triangulate."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest

from calibkit.calibrate.compare import compare_rigs, transform_camera
from calibkit.core.camera import Rig
from calibkit.core.recording import load_observations, load_truth_csv
from calibkit.synthetic import sim


@pytest.fixture()
def rig_file(tmp_path, calibkit_cli):
    res = calibkit_cli("sim", "rig", "--cameras", "8", "--out", tmp_path / "rig.toml")
    assert res.code == 0, res.err
    return tmp_path / "rig.toml"


def test_sim_scene_writes_recording_truth_and_its_rig(tmp_path, calibkit_cli) -> None:
    out = tmp_path / "take.mcrec"
    res = calibkit_cli("sim", "rigid", "--cameras", "5", "--frames", "40", "--bodies", "2",
                       "--noise-px", "0", "--out", out)
    assert res.code == 0, res.err
    rig = Rig.load(tmp_path / "take.rig.toml")
    assert len(rig) == 5
    truth = load_truth_csv(tmp_path / "take.truth.csv")
    obs, embedded = load_observations(out, rig)
    order_csv = np.lexsort((truth.marker, truth.frame))
    order_rec = np.lexsort((embedded.marker, embedded.frame))
    assert len(embedded) == len(truth) == 40 * 8  # 2 bodies of 4 markers, 40 frames
    assert np.allclose(embedded.xyz[order_rec], truth.xyz[order_csv], atol=1e-8)
    # a simulated observation reprojects its true point (noise 0)
    row = 0
    cam = rig[int(obs.camera[row])]
    xyz = truth.xyz[(truth.frame == obs.frame[row]) & (truth.marker == obs.marker[row])]
    assert np.allclose(cam.project(xyz)[0][0], obs.uv[row], atol=1e-3)  # file keeps 1e-4 px


def test_sim_errors_are_one_line(tmp_path, calibkit_cli) -> None:
    res = calibkit_cli("sim", "wand", "--cameras", "40", "--out", tmp_path / "w.mcrec")
    assert res.code == 2 and res.err.strip().count("\n") == 0
    assert "--cameras must be between 2 and 32" in res.err
    res = calibkit_cli("sim", "static", "--rig", tmp_path / "none.toml", "--out",
                       tmp_path / "s.mcrec")
    assert res.code == 2 and "no such rig file" in res.err


def test_rig_export_import_show(rig_file, tmp_path, calibkit_cli) -> None:
    res = calibkit_cli("rig", "export", rig_file, "--out", tmp_path / "rig.yaml")
    assert res.code == 0, res.err
    res = calibkit_cli("rig", "import", tmp_path / "rig.yaml", "--out", tmp_path / "back.toml")
    assert res.code == 0, res.err
    a, b = Rig.load(rig_file), Rig.load(tmp_path / "back.toml")
    assert all(np.allclose(x.K, y.K) and np.allclose(x.t, y.t) for x, y in zip(a, b,
                                                                               strict=True))
    res = calibkit_cli("rig", "show", rig_file, "--json", tmp_path / "show.json")
    assert res.code == 0 and "cam7" in res.out
    shown = json.loads((tmp_path / "show.json").read_text())
    assert np.allclose(shown["cameras"][3]["centre"], a[3].centre)
    # never overwrite the input, and say which suffix is wanted
    res = calibkit_cli("rig", "export", rig_file, "--out", rig_file)
    assert res.code == 2 and "expected a .yaml or .yml file" in res.err
    res = calibkit_cli("rig", "import", tmp_path / "rig.yaml", "--out", tmp_path / "x.yaml")
    assert res.code == 2 and "expected a .toml file" in res.err


def test_compare_reports_what_was_changed(rig_file, tmp_path, calibkit_cli) -> None:
    rig = Rig.load(rig_file)
    cam = rig[2]
    moved = cam.replace(t=cam.t + cam.R @ np.array([0.0, 0.0, 0.0]) - cam.R @ [0.005, 0, 0],
                        fx=cam.fx * 1.01, fy=cam.fy * 1.01, cx=cam.cx + 3.0, cy=cam.cy - 4.0)
    changed = rig.replace_camera(moved)
    changed.save(tmp_path / "changed.toml")
    res = calibkit_cli("compare", rig_file, tmp_path / "changed.toml", "--no-align", "--json",
                       tmp_path / "c.json")
    assert res.code == 0, res.err
    data = json.loads((tmp_path / "c.json").read_text())
    by_name = {c["name"]: c for c in data["cameras"]}
    assert abs(by_name["cam2"]["position_mm"] - 5.0) < 1e-6
    assert abs(by_name["cam2"]["focal_pct"] - 1.0) < 1e-9
    assert abs(by_name["cam2"]["principal_px"] - 5.0) < 1e-9
    assert by_name["cam0"]["position_mm"] < 1e-9 and data["grid_rms_mm"] > 0.1
    assert set(data) >= {"cameras", "grid_rms_mm", "alignment"}


def test_compare_aligns_a_rig_given_in_another_frame() -> None:
    """The same rig moved, turned and scaled: aligned, nothing is left but the scale."""
    rig = sim.make_rig(6, 4.0, seed=5)
    from scipy.spatial.transform import Rotation

    R = Rotation.from_rotvec([0.2, -0.4, 1.0]).as_matrix()
    other = Rig(tuple(transform_camera(c, R, np.array([1.0, 2.0, -0.5]), 1.3) for c in rig))
    result = compare_rigs(rig, other)
    assert max(c["position_mm"] for c in result["cameras"]) < 1e-6
    assert max(c["rotation_deg"] for c in result["cameras"]) < 1e-6
    assert result["grid_rms_mm"] < 1e-6
    assert abs(result["alignment"]["scale"] - 1 / 1.3) < 1e-9
    unaligned = compare_rigs(rig, other, align=False)
    assert unaligned["grid_rms_mm"] > 100


def test_convert_round_trip_and_errors(tmp_path, calibkit_cli) -> None:
    res = calibkit_cli("sim", "static", "--cameras", "3", "--frames", "5", "--out",
                       tmp_path / "s.mcrec")
    assert res.code == 0, res.err
    res = calibkit_cli("convert", tmp_path / "s.mcrec", "--out", tmp_path / "s.csv")
    assert res.code == 0, res.err
    with open(tmp_path / "s.csv", newline="") as handle:
        header = next(csv.reader(handle))
    assert header[:7] == ["frame", "camera", "t_ns", "u", "v", "area", "peak"]
    res = calibkit_cli("convert", tmp_path / "s.csv", "--out", tmp_path / "b.mcrec", "--rig",
                       tmp_path / "s.rig.toml")
    assert res.code == 0, res.err
    a, ta = load_observations(tmp_path / "s.mcrec")
    b, tb = load_observations(tmp_path / "b.mcrec")
    assert np.allclose(a.uv, b.uv, atol=1e-4) and np.array_equal(a.frame, b.frame)
    assert b.camera_sizes == a.camera_sizes and len(ta) == len(tb)
    res = calibkit_cli("convert", tmp_path / "s.csv", "--out", tmp_path / "s.csv")
    assert res.code == 2 and "is the input file" in res.err


def test_triangulate_command_against_truth(tmp_path, calibkit_cli) -> None:
    res = calibkit_cli("sim", "static", "--cameras", "8", "--markers", "30", "--frames", "10",
                       "--noise-px", "0.3", "--dropout", "0.2", "--ghosts", "2", "--out",
                       tmp_path / "s.mcrec")
    assert res.code == 0, res.err
    res = calibkit_cli("triangulate", "--rig", tmp_path / "s.rig.toml", "--from",
                       tmp_path / "s.mcrec", "--out", tmp_path / "p.csv", "--json",
                       tmp_path / "p.json")
    assert res.code == 0, res.err
    figures = json.loads((tmp_path / "p.json").read_text())
    assert figures["truth"]["recall_3"] >= 0.99
    assert figures["truth"]["ghost_fraction"] <= 0.005
    assert figures["truth"]["error_mm_rms"] < 3.0
    with open(tmp_path / "p.csv", newline="") as handle:
        rows = list(csv.DictReader(handle))
    assert len(rows) == figures["points"]
    assert list(rows[0])[:7] == ["frame", "x", "y", "z", "reproj_px", "ray_mm", "n_cameras"]
    assert int(rows[0]["n_cameras"]) == len(rows[0]["cameras"].split(";"))
    # errors a user can make
    res = calibkit_cli("triangulate", "--rig", tmp_path / "s.rig.toml", "--from",
                       tmp_path / "nothing.mcrec", "--out", tmp_path / "q.csv")
    assert res.code == 2 and "no such file" in res.err
    res = calibkit_cli("triangulate", "--rig", tmp_path / "s.rig.toml", "--from",
                       tmp_path / "s.mcrec", "--out", tmp_path / "q.csv", "--min-cameras", "1")
    assert res.code == 2 and "--min-cameras" in res.err
    other = sim.make_rig(3, 4.0, seed=9)
    other = Rig(tuple(c.replace(name=f"x{i}") for i, c in enumerate(other)))
    other.save(tmp_path / "other.toml")
    res = calibkit_cli("triangulate", "--rig", tmp_path / "other.toml", "--from",
                       tmp_path / "s.mcrec", "--out", tmp_path / "q.csv")
    assert res.code == 2 and "is not in the rig" in res.err
