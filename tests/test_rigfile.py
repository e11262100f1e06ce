"""rig.toml and OpenCV YAML rigs: round trips, what OpenCV reads, and errors a user can cause."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from calibkit.core.camera import BASLER_658x492_DIST, Rig
from calibkit.core.errors import UserError
from calibkit.synthetic import sim


@pytest.fixture()
def rig() -> Rig:
    return sim.make_rig(4, 3.0, (658, 492), 80.0, BASLER_658x492_DIST, seed=2)


def _same(a: Rig, b: Rig) -> None:
    assert a.names == b.names
    for ca, cb in zip(a, b, strict=True):
        assert ca.size == cb.size
        assert np.allclose(ca.K, cb.K, atol=1e-12)
        assert np.allclose(ca.dist, cb.dist, atol=1e-15)
        assert np.allclose(ca.R, cb.R, atol=1e-12)
        assert np.allclose(ca.t, cb.t, atol=1e-12)


def test_toml_round_trip_keeps_every_value_and_the_quality(rig, tmp_path) -> None:
    rig = Rig(rig.cameras, quality={"rms_px": 0.1234, "per_camera": [1.0, 2.0]},
              meta={"source": "test"})
    rig.save(tmp_path / "rig.toml")
    back = Rig.load(tmp_path / "rig.toml")
    _same(rig, back)
    assert back.quality["rms_px"] == 0.1234
    assert back.meta["source"] == "test" and "created" in back.meta
    assert [p.name for p in tmp_path.iterdir()] == ["rig.toml"]  # no temporary file left


def test_yaml_is_what_opencv_reads(rig, tmp_path) -> None:
    path = tmp_path / "rig.yaml"
    rig.save(path)
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    seq = fs.getNode("cameras")
    assert seq.size() == len(rig)
    for i, cam in enumerate(rig):
        node = seq.at(i)
        assert node.getNode("name").string() == cam.name
        assert [int(node.getNode("size").at(j).real()) for j in range(2)] == list(cam.size)
        assert np.allclose(node.getNode("K").mat(), cam.K)
        assert np.allclose(node.getNode("dist").mat().ravel(), cam.dist)
        assert node.getNode("dist").mat().shape == (1, 5)
        assert np.allclose(node.getNode("R").mat(), cam.R)
        assert np.allclose(node.getNode("t").mat().ravel(), cam.t)
    fs.release()
    # and the projection OpenCV makes with those values is ours
    xyz = np.array([[0.1, 0.2, 0.5], [-0.3, 0.1, 0.9]])
    cam = rig[1]
    uv_cv, _ = cv2.projectPoints(xyz, cv2.Rodrigues(cam.R)[0], cam.t, cam.K, cam.dist)
    assert np.allclose(uv_cv.reshape(-1, 2), cam.project(xyz)[0], atol=1e-9)
    _same(rig, Rig.load(path))


@pytest.mark.parametrize("edit, message", [
    (lambda s: s.replace("K = ", "K_missing = ", 1), "camera 'cam0': field 'K' is missing"),
    (lambda s: s.replace('name = "cam1"', 'name = "cam0"'), "camera name 'cam0' is used twice"),
    (lambda s: s.replace("dist = [", "dist = [1.0, ", 1), "camera 'cam0': field 'dist'"),
    (lambda s: s.replace("size = [", "size = [-1, ", 1), "camera 'cam0': field 'size'"),
    (lambda s: s.replace("[[cameras]]", "[[lenses]]"), "no [[cameras]] tables"),
    (lambda s: s + "\n[[[bad", "not valid TOML"),
])
def test_a_broken_rig_file_names_file_camera_and_field(rig, tmp_path, edit, message) -> None:
    path = tmp_path / "rig.toml"
    rig.save(path)
    path.write_text(edit(path.read_text()))
    with pytest.raises(UserError) as err:
        Rig.load(path)
    text = str(err.value)
    assert message in text and str(path) in text and "\n" not in text


def test_missing_rig_file_and_non_rotation(tmp_path) -> None:
    with pytest.raises(UserError, match="no such rig file"):
        Rig.load(tmp_path / "none.toml")
    text = """[[cameras]]
name = "a"
size = [640, 480]
K = [[500, 0, 320], [0, 500, 240], [0, 0, 1]]
dist = [0, 0, 0, 0, 0]
R = [[1, 0, 0], [0, 1, 0], [0, 0, 2]]
t = [0, 0, 0]
"""
    (tmp_path / "r.toml").write_text(text)
    with pytest.raises(UserError, match="camera 'a': field 'R' is not a rotation matrix"):
        Rig.load(tmp_path / "r.toml")
