"""`calibkit compare` sees scale: a rig 0.3 % too large is reported as such and judged for it,
and --no-scale leaves the error in the grid RMS (issue 28)."""

from __future__ import annotations

import json

import numpy as np
from scipy.spatial.transform import Rotation

from calibkit.calibrate.compare import GRADES, compare_rigs, transform_camera
from calibkit.core.camera import Rig
from calibkit.synthetic import sim

SCALE = 1.003  # the rig measures every length 0.3 % too long (12 mm over 4 m)
NOISE_M = 5e-5  # each calibrated camera centre off by this per axis
NOISE_DEG = 0.001  # and turned by this per axis


def calibrated(truth: Rig, seed: int) -> Rig:
    """A rig as a good calibration gives it: every camera a little off (NOISE_M, NOISE_DEG),
    then the whole rig in a frame of its own (turned, moved)."""
    rng = np.random.default_rng(seed)
    cams = []
    for cam in truth:
        R = Rotation.from_rotvec(np.radians(rng.normal(0, NOISE_DEG, 3))).as_matrix() @ cam.R
        centre = cam.centre + rng.normal(0, NOISE_M, 3)
        cams.append(cam.replace(R=R, t=-R @ centre))
    R = Rotation.from_rotvec([0.1, -0.2, 0.7]).as_matrix()
    return Rig(tuple(transform_camera(c, R, np.array([0.4, -1.0, 0.2]), 1.0) for c in cams),
               meta=dict(truth.meta))


def scaled(rig: Rig, s: float) -> Rig:
    return Rig(tuple(transform_camera(c, np.eye(3), np.array([0.3, 0.1, 0.0]), s) for c in rig),
               meta=dict(rig.meta))


def scale_sigma_ppm(truth: Rig) -> float:
    """The scale's own noise from NOISE_M on the centres (Umeyama: about sigma over the
    centres' root-sum-square spread)."""
    c = truth.centres()
    return 1e6 * NOISE_M / float(np.sqrt(np.sum((c - c.mean(axis=0)) ** 2)))


def test_a_scaled_rig_reports_its_scale_and_is_not_excellent() -> None:
    truth = sim.make_rig(6, 4.0, seed=3)
    good = calibrated(truth, seed=1)
    fine = compare_rigs(truth, good)
    assert fine["verdict"]["grade"] == "excellent", fine["verdict"]
    tol = 5 * scale_sigma_ppm(truth)
    assert abs(fine["scale"]["error_ppm"]) < tol

    big = compare_rigs(truth, scaled(good, SCALE))
    sc = big["scale"]
    assert abs(sc["error_ppm"] - 3000.0) < tol, (sc["error_ppm"], tol)
    assert sc["applied"] and abs(big["alignment"]["scale"] - 1 / SCALE) < tol * 1e-6
    # the similarity hides it from the grid RMS; the verdict does not
    assert big["grid_rms_mm"] < GRADES[0][1]
    assert big["verdict"]["grade"] != "excellent" and "scale" in big["verdict"]["reason"]
    # what the scale costs over the volume: 0.3 % of the grid's diagonal
    assert abs(sc["length_error_mm"] - 3.0 * sc["span_m"]) < tol * 1e-3 * sc["span_m"]
    # a rig too small by as much is judged the same
    small = compare_rigs(truth, scaled(good, 1 / SCALE))
    assert abs(small["scale"]["error_ppm"] + 3000.0) < tol + 10
    assert small["verdict"]["grade"] == big["verdict"]["grade"]


def test_no_scale_leaves_the_error_in_the_grid_rms() -> None:
    truth = sim.make_rig(6, 4.0, seed=3)
    good = calibrated(truth, seed=2)
    rigid_good = compare_rigs(truth, good, scale=False)
    rigid_big = compare_rigs(truth, scaled(good, SCALE), scale=False)
    assert not rigid_big["alignment"]["with_scale"] and rigid_big["alignment"]["scale"] == 1.0
    assert rigid_good["grid_rms_mm"] < GRADES[0][1]
    # a rigid alignment cannot do better than the scale's own spread about the grid middle
    assert rigid_big["grid_rms_mm"] >= 0.9 * rigid_big["scale"]["grid_rms_mm"] > 1.0
    assert rigid_big["verdict"]["grade"] not in ("excellent", "good")
    # the scale is still reported, not applied
    assert abs(rigid_big["scale"]["error_ppm"] - 3000.0) < 5 * scale_sigma_ppm(truth)
    assert not rigid_big["scale"]["applied"]


def test_compare_command_prints_and_writes_the_scale(tmp_path, calibkit_cli) -> None:
    truth = sim.make_rig(5, 4.0, seed=7)
    truth.save(tmp_path / "truth.toml")
    scaled(calibrated(truth, seed=4), SCALE).save(tmp_path / "big.toml")
    res = calibkit_cli("compare", tmp_path / "truth.toml", tmp_path / "big.toml", "--json",
                       tmp_path / "c.json")
    assert res.code == 0, res.err
    data = json.loads((tmp_path / "c.json").read_text())
    ppm = data["scale"]["error_ppm"]
    assert abs(ppm - 3000.0) < 5 * scale_sigma_ppm(truth)
    line = next(ln for ln in res.out.splitlines() if ln.startswith("scale:"))
    assert f"{ppm:+.0f} ppm" in line and f"{data['scale']['length_error_mm']:.2f} mm" in line
    verdict = next(ln for ln in res.out.splitlines() if ln.startswith("verdict:"))
    assert data["verdict"]["grade"] in verdict and data["verdict"]["grade"] != "excellent"

    res = calibkit_cli("compare", tmp_path / "truth.toml", tmp_path / "big.toml", "--no-scale",
                       "--json", tmp_path / "r.json")
    assert res.code == 0, res.err
    rigid = json.loads((tmp_path / "r.json").read_text())
    assert rigid["grid_rms_mm"] > 20 * data["grid_rms_mm"]
    assert rigid["grid_rms_mm"] >= 0.9 * rigid["scale"]["grid_rms_mm"]
    assert "no scale (--no-scale)" in res.out


def test_compare_command_refuses_rigs_without_a_common_camera(tmp_path, calibkit_cli) -> None:
    truth = sim.make_rig(3, 4.0, seed=1)
    truth.save(tmp_path / "a.toml")
    Rig(tuple(c.replace(name=f"other{i}") for i, c in enumerate(truth))).save(tmp_path / "b.toml")
    res = calibkit_cli("compare", tmp_path / "a.toml", tmp_path / "b.toml")
    assert res.code == 2
    assert len(res.err.strip().splitlines()) == 1 and "no camera name in common" in res.err


def test_one_camera_in_common_has_no_scale() -> None:
    truth = sim.make_rig(4, 4.0, seed=2)
    one = Rig((scaled(truth, SCALE)[0],))
    res = compare_rigs(truth, one)
    assert res["scale"]["error_ppm"] is None and not res["alignment"]["with_scale"]
