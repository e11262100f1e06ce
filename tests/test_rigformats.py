"""Other tools' calibration files: values read by hand from real files, conventions proved on
their data, round trips, and the one-line errors a broken file gives."""

from __future__ import annotations

import csv
import shutil
from pathlib import Path

import numpy as np
import pytest

from calibkit.core.camera import Rig
from calibkit.core.errors import UserError
from calibkit.core.rigformats.caliscope import read_caliscope, write_caliscope

ROOT = Path(__file__).resolve().parents[1]
CALISCOPE = ROOT / "fixtures" / "caliscope_4_cam_recording"


def _same(a: Rig, b: Rig, tol: float = 1e-9) -> None:
    assert a.names == b.names
    for ca, cb in zip(a, b, strict=True):
        assert ca.size == cb.size
        np.testing.assert_allclose(cb.K, ca.K, rtol=tol, atol=tol)
        np.testing.assert_allclose(cb.dist, ca.dist, rtol=tol, atol=tol)
        np.testing.assert_allclose(cb.R, ca.R, rtol=tol, atol=tol)
        np.testing.assert_allclose(cb.t, ca.t, rtol=tol, atol=tol)


# ---- caliscope ------------------------------------------------------------------------------

def test_caliscope_values_read_by_hand():
    rig = read_caliscope(CALISCOPE / "camera_array.toml")
    assert rig.names == ["cam_0", "cam_1", "cam_2", "cam_3"]
    cam = rig["cam_2"]  # [cameras.2] in camera_array.toml
    assert cam.size == (1280, 720)
    assert cam.fx == pytest.approx(637.2292860850233, abs=1e-12)
    assert cam.fy == pytest.approx(633.5719552845733, abs=1e-12)
    assert (cam.cx, cam.cy) == pytest.approx((657.4323077978876, 378.1791029421547), abs=1e-12)
    assert cam.dist[3] == pytest.approx(0.012510062186129272, abs=1e-15)  # p2
    assert cam.dist[4] == pytest.approx(0.15631917743880638, abs=1e-15)  # k3
    # the centre -R^T t from the file's rotation and translation, worked by hand
    R = np.array([[-0.9967644634943604, -0.07540940912751744, 0.027821310713882212],
                  [-0.06836124744416018, 0.6132863527233845, -0.7868968098875017],
                  [0.04227699330224407, -0.7862526760388718, -0.6164571236177216]])
    t = np.array([0.038133706887563415, 0.6725515804052516, 1.5183602439910873])
    np.testing.assert_allclose(cam.centre, -R.T @ t, atol=1e-12)
    np.testing.assert_allclose(cam.centre, [0.0198, 0.7842, 1.4642], atol=1e-4)
    assert rig.meta["caliscope"]["cam_1"]["rotation_count"] == -1
    assert rig.meta["caliscope"]["cam_2"]["rotation_count"] == 1


def test_caliscope_older_config_layout_gives_the_same_cameras():
    """config.toml holds the same cameras as [cam_N] tables (an older caliscope's layout)."""
    _same(read_caliscope(CALISCOPE / "camera_array.toml"),
          read_caliscope(CALISCOPE / "config.toml"), tol=1e-12)


def _stereo_points() -> dict[str, np.ndarray]:
    with open(CALISCOPE / "calibration" / "extrinsic" / "stereotriangulated_points.csv",
              newline="") as handle:
        rows = list(csv.DictReader(handle))
    keys = ("x_pos", "y_pos", "z_pos", "x_A", "y_A", "x_B", "y_B", "cam_id_A", "cam_id_B")
    return {k: np.array([float(r[k]) for r in rows]) for k in keys}


def _reprojection_errors(rig: Rig) -> dict[int, np.ndarray]:
    """Per camera id: pixel distance between caliscope's stored pixel of each triangulated
    point and the point projected through `rig`."""
    pts = _stereo_points()
    xyz = np.stack([pts["x_pos"], pts["y_pos"], pts["z_pos"]], axis=1)
    errors: dict[int, list] = {}
    for side in "AB":
        for cam_id in np.unique(pts[f"cam_id_{side}"]).astype(int):
            rows = pts[f"cam_id_{side}"] == cam_id
            uv, in_front = rig[f"cam_{cam_id}"].project(xyz[rows])
            seen = np.stack([pts[f"x_{side}"][rows], pts[f"y_{side}"][rows]], axis=1)
            err = np.linalg.norm(uv - seen, axis=1)
            errors.setdefault(cam_id, []).append(np.where(in_front, err, np.inf))
    return {k: np.concatenate(v) for k, v in errors.items()}


def test_caliscope_pose_is_world_to_camera_proved_by_its_own_triangulation():
    """caliscope's triangulated board corners land on the pixels it stored for them when
    projected through the imported rig (world-to-camera read as ours); read the other way
    (camera-to-world) every camera but the anchor at the origin misses by tens of pixels.

    The points were triangulated by pairs, so each pixel carries the pair's residual (the
    cameras' intrinsic RMS is 0.2-0.7 px): medians of a few pixels, not of zero."""
    rig = read_caliscope(CALISCOPE / "camera_array.toml")
    errors = _reprojection_errors(rig)
    assert sorted(errors) == [0, 1, 2, 3]
    for cam_id, err in errors.items():
        assert np.median(err) < 4.0, (cam_id, np.median(err))
        assert np.percentile(err, 95) < 6.0, (cam_id, np.percentile(err, 95))
    inverted = Rig(tuple(c.replace(R=c.R.T, t=c.centre) for c in rig))
    wrong = _reprojection_errors(inverted)
    for cam_id in (0, 2, 3):  # cam_1 is caliscope's anchor: R ~ I, t ~ 0 either way
        assert np.median(wrong[cam_id]) > 50.0, cam_id


def test_caliscope_rotation_count_leaves_the_sensor_frame_alone():
    """Cameras turned in caliscope's UI (rotation_count +-1) store pixels spanning the
    unturned 1280 x 720 frame (x beyond 720): size and intrinsics are the sensor's."""
    pts = _stereo_points()
    rig = read_caliscope(CALISCOPE / "camera_array.toml")
    for cam_id in (1, 2):
        assert rig.meta["caliscope"][f"cam_{cam_id}"]["rotation_count"] != 0
        xs = np.concatenate([pts[f"x_{s}"][pts[f"cam_id_{s}"] == cam_id] for s in "AB"])
        assert xs.max() > 720.0 and xs.max() < 1280.0
        assert rig[f"cam_{cam_id}"].size == (1280, 720)


def test_caliscope_round_trip(tmp_path):
    rig = read_caliscope(CALISCOPE / "camera_array.toml")
    write_caliscope(rig, tmp_path / "camera_array.toml")
    back = read_caliscope(tmp_path / "camera_array.toml")
    _same(rig, back)
    assert back.meta["caliscope"] == rig.meta["caliscope"]  # rotation_count, error travel


def test_caliscope_ignored_and_uncalibrated_cameras_are_skipped_and_listed(tmp_path):
    text = (CALISCOPE / "camera_array.toml").read_text()
    text = text.replace("[cameras.1]\ncam_id = 1\nrotation_count = -1\nerror = 0.469\n"
                        "exposure = -6.0\ngrid_count = 34\nignore = false",
                        "[cameras.1]\ncam_id = 1\nrotation_count = -1\nerror = 0.469\n"
                        "exposure = -6.0\ngrid_count = 34\nignore = true")
    assert "ignore = true" in text
    start = text.index("[cameras.3]")
    cam3 = text[start:]
    cam3 = "\n".join(line for line in cam3.splitlines()
                     if not line.startswith(("rotation =", "translation =")))
    path = tmp_path / "camera_array.toml"
    path.write_text(text[:start] + cam3 + "\n")
    rig = read_caliscope(path)
    assert rig.names == ["cam_0", "cam_2"]
    assert rig.meta["skipped_cameras"] == ["cam_1: ignore = true",
                                           "cam_3: no rotation, translation (not calibrated)"]


@pytest.mark.parametrize("edit, message", [
    (("translation = [-0.6425176710599999,", "translation = [nan,"), "not a finite number"),
    (("rotation = [[0.028454458274723926,", "rotation = [[0.528454458274723926,"),
     "not a rotation matrix"),
    (("size = [1280, 720]\nmatrix = [[894.5", "size = [1280]\nmatrix = [[894.5"),
     "'size' must be 2 numbers"),
    (("matrix = [[894.5288733178912, 0.0, 624.011791468827]",
      "matrix = [[-894.5288733178912, 0.0, 624.011791468827]"), "positive focal lengths"),
    (("size = [1280, 720]\nmatrix = [[894.5", "size = [600, 1280]\nmatrix = [[894.5"),
     r"principal point \(624.012, 361.282\) lies outside the 600x1280 image"),
    (("[cameras.0]", "[cameras.0"), "not valid TOML"),
])
def test_caliscope_broken_file_gives_one_line_naming_file_and_camera(tmp_path, edit, message):
    text = (CALISCOPE / "camera_array.toml").read_text()
    assert edit[0] in text
    path = tmp_path / "camera_array.toml"
    path.write_text(text.replace(edit[0], edit[1], 1))
    with pytest.raises(UserError, match=message) as info:
        read_caliscope(path)
    assert str(path) in str(info.value) and "\n" not in str(info.value)
    if "TOML" not in message:
        assert "[0]" in str(info.value)


def test_caliscope_not_a_caliscope_file(tmp_path):
    path = tmp_path / "other.toml"
    shutil.copy(ROOT / "fixtures" / "wand_rig_8cam.toml", path)
    with pytest.raises(UserError, match="camera_array.toml"):
        read_caliscope(path)
    with pytest.raises(UserError, match="no such file"):
        read_caliscope(tmp_path / "none.toml")
