"""Other tools' calibration files: values read by hand from real files, conventions proved on
their data, round trips, and the one-line errors a broken file gives."""

from __future__ import annotations

import csv
import re
import shutil
from pathlib import Path

import numpy as np
import pytest

from calibkit.core.camera import Rig
from calibkit.core.errors import UserError
from calibkit.core.rigformats import detect_format, read_rig_file, write_rig_file
from calibkit.core.rigformats.anipose import read_anipose
from calibkit.core.rigformats.caliscope import read_caliscope, write_caliscope
from calibkit.core.rigformats.pose2sim import read_pose2sim
from calibkit.core.rigformats.qca import read_qca

ROOT = Path(__file__).resolve().parents[1]
CALISCOPE = ROOT / "fixtures" / "caliscope_4cam"


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


def test_caliscope_port_and_rodrigues_layout_gives_the_same_cameras(tmp_path):
    """Other caliscope versions write `port` for cam_id, `rotation` as a Rodrigues vector
    and `"null"` for unset values: the same cameras come out."""
    rig = read_caliscope(CALISCOPE / "camera_array.toml")
    lines = []
    for cam in rig:
        cam_id = int(cam.name.removeprefix("cam_"))
        lines += [f"[cameras.{cam_id}]", f"port = {cam_id}", "rotation_count = 0",
                  'exposure = "null"', f"size = [{cam.width}, {cam.height}]",
                  f"matrix = {cam.K.tolist()}", f"distortions = {cam.dist.tolist()}",
                  f"translation = {cam.t.tolist()}", f"rotation = {cam.rvec.tolist()}", ""]
    path = tmp_path / "camera_array.toml"
    path.write_text("\n".join(lines))
    _same(rig, read_caliscope(path), tol=1e-12)


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


# ---- Pose2Sim and anipose (files written by hand from their published layouts) ------------

# Pose2Sim's layout: one table per camera named after it, size [width, height] as floats,
# k1 k2 p1 p2, Rodrigues rotation, translation in metres, fisheye = false, [metadata].
POSE2SIM = """\
[cam_01]
name = "cam_01"
size = [ 1088.0, 1920.0]
matrix = [ [ 1681.5, 0.0, 533.0], [ 0.0, 1681.0, 948.0], [ 0.0, 0.0, 1.0]]
distortions = [ -0.046, 0.14, 0.0006, 0.0007]
rotation = [ 0.0, 0.0, 0.0]
translation = [ 0.1, -0.2, 3.0]
fisheye = false

[cam_02]
name = "cam_02"
size = [ 1920.0, 1080.0]
matrix = [ [ 1400.0, 0.0, 960.0], [ 0.0, 1400.0, 540.0], [ 0.0, 0.0, 1.0]]
distortions = [ 0.01, -0.02, 0.0, 0.0]
rotation = [ 3.141592653589793, 0.0, 0.0]
translation = [ 0.0, 0.0, 2.0]
fisheye = false

[metadata]
adjusted = false
error = 0.0
"""

# aniposelib's CameraGroup.dump: [cam_N] tables in order with the camera's name inside,
# integer size [width, height], five coefficients, no fisheye key on pinhole cameras,
# translation in the board's unit (mm here), [metadata]; its TOML writer ends arrays ",]".
ANIPOSE = """\
[cam_0]
name = "A"
size = [ 1440, 1080,]
matrix = [ [ 1852.4, 0.0, 719.5,], [ 0.0, 1852.4, 539.5,], [ 0.0, 0.0, 1.0,],]
distortions = [ -0.036, 0.0, 0.0, 0.0, 0.0,]
rotation = [ 0.0, 0.0, 0.0,]
translation = [ 100.0, -200.0, 3000.0,]

[cam_1]
name = "B"
size = [ 1440, 1080,]
matrix = [ [ 1935.9, 0.0, 719.5,], [ 0.0, 1935.9, 539.5,], [ 0.0, 0.0, 1.0,],]
distortions = [ -0.31, 0.05, 0.001, -0.002, 0.01,]
rotation = [ 3.141592653589793, 0.0, 0.0,]
translation = [ 0.0, 0.0, 2000.0,]

[metadata]
adjusted = true
error = 1.668
"""


@pytest.fixture
def pose2sim_file(tmp_path) -> Path:
    path = tmp_path / "Calib.toml"
    path.write_text(POSE2SIM)
    return path


@pytest.fixture
def anipose_file(tmp_path) -> Path:
    path = tmp_path / "calibration.toml"
    path.write_text(ANIPOSE)
    return path


def test_pose2sim_values_read_by_hand(pose2sim_file):
    rig = read_pose2sim(pose2sim_file)
    assert rig.names == ["cam_01", "cam_02"]
    a, b = rig
    assert a.size == (1088, 1920) and b.size == (1920, 1080)
    assert (a.fx, a.fy, a.cx, a.cy) == (1681.5, 1681.0, 533.0, 948.0)
    np.testing.assert_array_equal(a.dist, [-0.046, 0.14, 0.0006, 0.0007, 0.0])
    np.testing.assert_allclose(a.centre, [-0.1, 0.2, -3.0], atol=1e-15)  # R = I
    # rotated pi about x: R = diag(1, -1, -1), a camera 2 m up looking down
    np.testing.assert_allclose(b.R, np.diag([1.0, -1.0, -1.0]), atol=1e-15)
    np.testing.assert_allclose(b.centre, [0.0, 0.0, 2.0], atol=1e-15)
    assert rig.meta["pose2sim"] == {"adjusted": False, "error": 0.0}


def test_anipose_values_read_by_hand_in_the_boards_unit(anipose_file):
    rig = read_anipose(anipose_file)  # mm, anipose's examples' unit
    assert rig.names == ["A", "B"]
    a, b = rig
    assert a.size == (1440, 1080) and (a.fx, a.cx, a.cy) == (1852.4, 719.5, 539.5)
    np.testing.assert_allclose(a.centre, [-0.1, 0.2, -3.0], atol=1e-15)
    np.testing.assert_allclose(b.centre, [0.0, 0.0, 2.0], atol=1e-15)
    np.testing.assert_array_equal(b.dist, [-0.31, 0.05, 0.001, -0.002, 0.01])
    np.testing.assert_allclose(read_anipose(anipose_file, "cm")["A"].t, [1.0, -2.0, 30.0],
                               atol=1e-12)
    np.testing.assert_allclose(read_anipose(anipose_file, "m")["A"].t, [100.0, -200.0, 3000.0])


def test_auto_detection_tells_the_layouts_apart(pose2sim_file, anipose_file):
    assert detect_format(pose2sim_file) == "pose2sim"
    assert detect_format(anipose_file) == "anipose"
    # an older Pose2Sim file without `fisheye`: its tables are named after the cameras
    pose2sim_file.write_text(POSE2SIM.replace("fisheye = false\n", ""))
    assert detect_format(pose2sim_file) == "pose2sim"
    # an anipose file with a fisheye camera is still anipose (and refused when read)
    anipose_file.write_text(ANIPOSE.replace('name = "B"', 'name = "B"\nfisheye = true'))
    assert detect_format(anipose_file) == "anipose"
    assert detect_format(CALISCOPE / "camera_array.toml") == "caliscope"
    assert detect_format(CALISCOPE / "config.toml") == "caliscope"
    assert detect_format(QCA) == "qca"
    assert detect_format(ROOT / "fixtures" / "wand_rig_8cam.toml") == "calibkit"


def test_fisheye_cameras_are_refused_clearly(anipose_file):
    text = ANIPOSE.replace('name = "B"', 'name = "B"\nfisheye = true')
    anipose_file.write_text(text)
    with pytest.raises(UserError, match=r"camera \[cam_1\] is a fisheye camera"):
        read_anipose(anipose_file)


@pytest.mark.parametrize("edit, message", [
    (("translation = [ 0.1, -0.2, 3.0]", "translation = [ 0.1, -0.2]"),
     r"\[cam_01\] 'translation' must be 3 numbers"),
    (("translation = [ 0.1, -0.2, 3.0]", "translation = [ 0.1, -0.2, inf]"),
     "not a finite number"),
    (("rotation = [ 0.0, 0.0, 0.0]", "rotation = [[2.0, 0, 0], [0, 1, 0], [0, 0, 1]]"),
     "not a rotation matrix"),
    (("rotation = [ 0.0, 0.0, 0.0]\n", ""), r"\[cam_01\]: 'rotation' is missing"),
    (("distortions = [ -0.046, 0.14, 0.0006, 0.0007]", "distortions = [ -0.046, 0.14]"),
     "at least 4 coefficients"),
    (("distortions = [ -0.046, 0.14, 0.0006, 0.0007]",
      "distortions = [ -0.046, 0.14, 0.0006, 0.0007, 0.0, 0.1, 0.0, 0.0]"),
     "only OpenCV's five-coefficient model"),
    (("matrix = [ [ 1681.5, 0.0, 533.0]", "matrix = [ [ 1681.5, 0.0, 533.0, 1.0]"),
     r"'matrix' must be numbers shaped \[3, 3\]"),
    (("size = [ 1088.0, 1920.0]", "size = [ 1088.5, 1920.0]"), "two positive whole numbers"),
])
def test_pose2sim_broken_file_gives_one_line(pose2sim_file, edit, message):
    assert edit[0] in POSE2SIM
    pose2sim_file.write_text(POSE2SIM.replace(edit[0], edit[1], 1))
    with pytest.raises(UserError, match=message) as info:
        read_pose2sim(pose2sim_file)
    assert str(pose2sim_file) in str(info.value) and "\n" not in str(info.value)


# ---- Qualisys QTM .qca -------------------------------------------------------------------

QCA = ROOT / "fixtures" / "pose2sim_chessboard_4cam" / "Calib.qca.txt"


def test_qca_values_read_by_hand():
    rig = read_qca(QCA)
    assert rig.names == ["cam01", "cam02", "cam03", "cam04"]
    cam = rig["cam01"]
    assert cam.size == (1088, 1920)  # fov_video 0..1087 x 0..1919
    assert cam.fx == pytest.approx(107599.671875 / 64, abs=1e-9)
    assert cam.fy == pytest.approx(107588.828125 / 64, abs=1e-9)
    assert (cam.cx, cam.cy) == pytest.approx((34110.316406 / 64, 60680.792969 / 64), abs=1e-9)
    np.testing.assert_array_equal(cam.dist, [-0.046183, 0.139983, 0.000608, 0.00069, 0.0])
    np.testing.assert_allclose(cam.centre, [1.4602323709212087, -1.9091590482454608,
                                            1.8965058524092062], atol=1e-12)
    # Pose2Sim's own conversion of this very file (Calib_qualisys.toml in its demo session)
    pose2sim = {
        "cam01": ([1.6882754799999993, 1.0483220499999997, -0.41955852000000016],
                  [0.3211048899999996, 0.9563320600000009, 2.8907130499999996]),
        "cam02": ([1.34975875, 1.5963809099999993, -1.1983285799999999],
                  [-0.11152829000000014, 0.7766184800000001, 3.0675519599999994]),
        "cam03": ([0.8109654899999995, -2.1972129299999996, 1.3760277799999996],
                  [-0.7934803899999995, 0.32283594000000126, 4.353514870000001]),
        "cam04": ([1.4045571699999995, -1.3887412699999993, 0.42535743000000026],
                  [0.5030217200000007, 0.04894934000000107, 4.406564460000002])}
    for name, (rvec, t) in pose2sim.items():
        np.testing.assert_allclose(rig[name].rvec, rvec, atol=1e-12)
        np.testing.assert_allclose(rig[name].t, t, atol=1e-12)
    assert rig.meta["qca"]["cam04"]["avg_residual_mm"] == 0.504772


def test_qca_cameras_look_into_the_volume():
    """The four cameras stand around the capture area 1.7-1.9 m up: each optical axis (the
    third row of R) points at the area's centre. Read without QTM's camera-axes flip, or
    with the orientation transposed, they look away or past it."""
    rig = read_qca(QCA)
    centre = np.array([0.0, 0.0, 1.0])
    for cam in rig:
        towards = (centre - cam.centre) / np.linalg.norm(centre - cam.centre)
        assert cam.R[2] @ towards > 0.9, cam.name
        assert cam.R[1] @ [0.0, 0.0, 1.0] < 0.0, cam.name  # image y points down the world


def _qca_text(**edits: str) -> str:
    text = QCA.read_text()
    for old, new in edits.values():
        assert old in text, old
        text = text.replace(old, new)
    return text


def test_qca_crop_window_pixel_units_and_video_resolution(tmp_path):
    """A file in pixels rather than 1/64 sub-pixels, a cropped video window and a camera
    filming at 540p of its 1080-line sensor: written by hand from the attributes' meaning."""
    cam01 = ('<fov_video bottom="1919" left="0" right="1087" top="0"/>', None)
    text = QCA.read_text()
    first = text.index('serial="cam01"')
    block_end = text.index("</camera>", first)
    block = text[first:block_end]
    block = block.replace('viewrotation="0"', 'viewrotation="0" video_resolution="540p"')
    block = block.replace(cam01[0], '<fov_video bottom="1819" left="100" right="1087" top="0"/>')
    for key, value in (("centerPointU", "34110.316406"), ("centerPointV", "60680.792969"),
                       ("focalLengthU", "107599.671875"), ("focalLengthV", "107588.828125")):
        block = block.replace(f'{key}="{value}"', f'{key}="{float(value) / 64!r}"')
    path = tmp_path / "crop.qca.txt"
    path.write_text(text[:first] + block + text[block_end:])
    cam = read_qca(path)["cam01"]
    assert cam.size == (494, 910)  # (988 x 1820 window) at 540 of 1080 lines
    assert cam.fx == pytest.approx(107599.671875 / 64 / 2, abs=1e-9)
    assert cam.cx == pytest.approx((34110.316406 / 64 - 100) / 2, abs=1e-9)
    assert cam.cy == pytest.approx(60680.792969 / 64 / 2, abs=1e-9)


def test_qca_inactive_camera_is_skipped_and_listed(tmp_path):
    path = tmp_path / "Calib.qca.txt"
    path.write_text(QCA.read_text().replace('active="1" avg-residual="0.444749"',
                                            'active="0" avg-residual="0.444749"'))
    rig = read_qca(path)
    assert rig.names == ["cam01", "cam03", "cam04"]
    assert rig.meta["skipped_cameras"] == ["cam02: active = 0"]


@pytest.mark.parametrize("old, new, message", [
    ('r33="0.3825762057979294"', 'r33="-0.3825762057979294"', "not a rotation matrix"),
    ('r33="0.3825762057979294"', "", "no 'r33' attribute"),
    ('focalLengthU="107599.671875"', 'focalLengthU="nan"', "not a finite number"),
    ('focalLengthU="107599.671875"', 'focalLengthU="big"', "must be a number"),
    ('<fov_video bottom="1919" left="0" right="1087" top="0"/>',
     '<fov_video bottom="1919" left="1087" right="0" top="0"/>', "right/bottom lie before"),
    ("</cameras>", "", "not valid XML"),
])
def test_qca_broken_file_gives_one_line(tmp_path, old, new, message):
    text = QCA.read_text()
    assert old in text
    path = tmp_path / "Calib.qca.txt"
    path.write_text(text.replace(old, new, 1))
    with pytest.raises(UserError, match=message) as info:
        read_qca(path)
    assert str(path) in str(info.value) and "\n" not in str(info.value)


# ---- round trips: import -> export -> import ------------------------------------------------

def _sources(tmp_path) -> dict[str, Rig]:
    (tmp_path / "p.toml").write_text(POSE2SIM)
    (tmp_path / "a.toml").write_text(ANIPOSE)
    return {"caliscope": read_caliscope(CALISCOPE / "camera_array.toml"),
            "qca": read_qca(QCA), "pose2sim": read_pose2sim(tmp_path / "p.toml"),
            "anipose": read_anipose(tmp_path / "a.toml")}


@pytest.mark.parametrize("fmt", ["opencv", "caliscope", "pose2sim", "anipose"])
def test_every_format_round_trips(tmp_path, fmt):
    suffix = ".yaml" if fmt == "opencv" else ".toml"
    for source, rig in _sources(tmp_path).items():
        for unit in (("mm", "cm", "m") if fmt == "anipose" else ("mm",)):
            out = tmp_path / f"{source}-{fmt}-{unit}{suffix}"
            write_rig_file(rig, out, fmt, unit)
            assert detect_format(out) == fmt
            back, found = read_rig_file(out, "auto", unit)
            assert found == fmt
            if fmt == "caliscope" and source != "caliscope":
                # caliscope numbers its cameras: cam_01 keeps its number, others count up
                expected = {"qca": ["cam_0", "cam_1", "cam_2", "cam_3"],
                            "pose2sim": ["cam_1", "cam_2"], "anipose": ["cam_0", "cam_1"]}
                assert back.names == expected[source]
                back = Rig(tuple(c.replace(name=n) for c, n in zip(back, rig.names,
                                                                    strict=True)))
            _same(rig, back)
    assert sorted(p.name for p in tmp_path.iterdir() if p.name.startswith(".")) == []


def test_export_refuses_qca_and_unknown_units(tmp_path):
    rig = read_qca(QCA)
    with pytest.raises(UserError, match="QTM files come from QTM"):
        write_rig_file(rig, tmp_path / "x.qca", "qca")
    with pytest.raises(UserError, match="--unit 'inch'"):
        write_rig_file(rig, tmp_path / "x.toml", "anipose", "inch")
    assert not list(tmp_path.iterdir())


def test_unknown_files_name_themselves(tmp_path):
    for name, text in (("notes.toml", 'title = "not a calibration"\n'),
                       ("page.xml", "<html><body/></html>"), ("data.bin", "\x00\x01 garbage")):
        path = tmp_path / name
        path.write_text(text)
        with pytest.raises(UserError, match="calibkit rea|calibkit recognises") as info:
            detect_format(path)
        assert str(path) in str(info.value)


# ---- the command line ----------------------------------------------------------------------

def test_cli_imports_each_format_by_content(tmp_path, calibkit_cli):
    (tmp_path / "Calib.toml").write_text(POSE2SIM)
    (tmp_path / "calibration.toml").write_text(ANIPOSE)
    for src, fmt in ((CALISCOPE / "camera_array.toml", "caliscope"), (QCA, "qca"),
                     (tmp_path / "Calib.toml", "pose2sim"),
                     (tmp_path / "calibration.toml", "anipose")):
        out = tmp_path / f"{fmt}.rig.toml"
        res = calibkit_cli("rig", "import", src, "--out", out)
        assert res.code == 0, res.err
        assert f"from {fmt}" in res.out
        _same(read_rig_file(src, fmt)[0], Rig.load(out))


def test_cli_exports_and_reimports(tmp_path, calibkit_cli):
    calibkit_cli("rig", "import", QCA, "--out", tmp_path / "rig.toml")
    for fmt in ("caliscope", "pose2sim", "anipose"):
        out = tmp_path / f"{fmt}.toml"
        res = calibkit_cli("rig", "export", tmp_path / "rig.toml", "--out", out, "--format",
                           fmt, "--unit", "cm")
        assert res.code == 0, res.err
        res = calibkit_cli("rig", "import", out, "--out", tmp_path / f"{fmt}.back.toml",
                           "--unit", "cm")
        assert res.code == 0 and f"from {fmt}" in res.out, res.err
        back = Rig.load(tmp_path / f"{fmt}.back.toml")
        np.testing.assert_allclose(back.centres(), read_qca(QCA).centres(), atol=1e-9)


def test_cli_broken_file_exits_non_zero_with_one_line(tmp_path, calibkit_cli):
    path = tmp_path / "camera_array.toml"
    path.write_text((CALISCOPE / "camera_array.toml").read_text().replace(
        "translation = [-0.6425176710599999,", "translation = [nan,"))
    res = calibkit_cli("rig", "import", path, "--out", tmp_path / "rig.toml")
    assert res.code == 2
    lines = res.err.strip().splitlines()
    assert len(lines) == 1 and str(path) in lines[0] and "finite" in lines[0], res.err
    assert "Traceback" not in res.err and not (tmp_path / "rig.toml").exists()
    for args, message in (
            (("import", QCA, "--out", tmp_path / "r.toml", "--format", "vicon"), "'vicon'"),
            (("export", tmp_path / "r.toml", "--out", tmp_path / "x.toml"), ".yaml or .yml"),
            (("export", path, "--out", path, "--format", "caliscope"), "is the input file"),
            (("export", path, "--out", tmp_path / "q.qca", "--format", "qca"), "come from QTM"),
            (("import", tmp_path / "none.toml", "--out", tmp_path / "r.toml"), "no such file")):
        res = calibkit_cli("rig", *args)
        assert res.code == 2 and message in res.err, (args, res.err)
        assert len(res.err.strip().splitlines()) == 1


def _mutations(text: str, xml: bool):
    """Each line deleted; each TOML value (or XML attribute) replaced by a wrong kind."""
    lines = text.splitlines()
    for i, line in enumerate(lines):
        yield "\n".join(lines[:i] + lines[i + 1:])
        if not xml and "=" in line:
            key = line.split("=", 1)[0]
            for wrong in ('"x"', "1e999", "[[1, 2], [3]]"):
                yield "\n".join(lines[:i] + [f"{key}= {wrong}"] + lines[i + 1:])
        if xml:
            for match in re.finditer(r'"[-0-9.]+"', line):
                for wrong in ('"abc"', '"1e400"'):
                    edited = line[:match.start()] + wrong + line[match.end():]
                    yield "\n".join(lines[:i] + [edited] + lines[i + 1:])


@pytest.mark.parametrize("source", ["caliscope", "config", "qca", "pose2sim", "anipose"])
def test_any_damage_reads_or_gives_one_line_never_a_traceback(tmp_path, source):
    """Every file of the kind survives: a damaged copy reads, or ends in one UserError."""
    text = {"caliscope": lambda: (CALISCOPE / "camera_array.toml").read_text(),
            "config": lambda: (CALISCOPE / "config.toml").read_text(),
            "qca": QCA.read_text, "pose2sim": lambda: POSE2SIM,
            "anipose": lambda: ANIPOSE}[source]()
    fmt = {"config": "caliscope"}.get(source, source)
    path = tmp_path / ("calib.qca.txt" if source == "qca" else "calib.toml")
    refused = 0
    for n, damaged in enumerate(_mutations(text, xml=source == "qca")):
        path.write_text(damaged)
        try:
            read_rig_file(path, fmt)
        except UserError as exc:
            refused += 1
            assert "\n" not in str(exc), (n, str(exc))
    assert refused > 20  # damage was met (and any other exception fails the test)
