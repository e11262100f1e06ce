"""Cameras read what we write: images, folders, videos; missing inputs are user errors."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from calibkit.cameras import open_camera
from calibkit.cameras.images import FolderSource, ImageSource
from calibkit.cameras.opencv import DeviceSource
from calibkit.cameras.video import VideoSource
from calibkit.core.camera import Camera
from calibkit.core.errors import UserError
from calibkit.synthetic import frames as frames_module
from calibkit.synthetic.frames import SimSource
from calibkit.synthetic.spots import render_spots
from calibkit.synthetic.truthcheck import match_to_truth
from calibkit.vision.detect import detect


def _frame(seed: int, size=(160, 120)):
    rng = np.random.default_rng(seed)
    # Three markers in three separate bands, so they never touch.
    band = size[0] / 3
    uv = np.stack([np.arange(3) * band + rng.uniform(12, band - 12, 3),
                   rng.uniform(12, size[1] - 12, 3)], axis=1)
    return render_spots(size, uv, 3.0, rng=seed), uv


def test_image_source_reads_gray_and_colour(tmp_path):
    img, _ = _frame(0)
    cv2.imwrite(str(tmp_path / "gray.png"), img)
    colour = cv2.merge([img, img // 2, img])
    cv2.imwrite(str(tmp_path / "colour.png"), colour)
    frames = list(ImageSource(tmp_path / "gray.png"))
    assert len(frames) == 1 and frames[0].camera == "gray" and frames[0].index == 0
    assert np.array_equal(frames[0].image, img)
    (frame,) = open_camera(tmp_path / "colour.png")
    assert np.array_equal(frame.image, colour)
    (tmp_path / "broken.png").write_bytes(b"not a png")
    with pytest.raises(UserError):
        list(ImageSource(tmp_path / "broken.png"))


def test_folder_source_natural_order_and_timestamps(tmp_path):
    truths = {}
    for i in (1, 2, 10):
        img, uv = _frame(i)
        cv2.imwrite(str(tmp_path / f"frame{i}.png"), img)
        truths[i] = uv
    (tmp_path / "notes.txt").write_text("not an image")
    src = open_camera(tmp_path, fps=50.0)
    assert isinstance(src, FolderSource)
    frames = list(src)
    assert [f.index for f in frames] == [0, 1, 2]
    assert [f.t_ns for f in frames] == [0, 20_000_000, 40_000_000]
    for f, i in zip(frames, (1, 2, 10), strict=True):
        b = detect(f.image)
        det, _ = match_to_truth(b.uv, truths[i], max_dist_px=0.2)
        assert len(det) == 3


def test_video_source_round_trip(tmp_path):
    path = tmp_path / "clip.avi"
    size = (160, 120)
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 25.0, size)
    assert writer.isOpened()
    truths = []
    for i in range(5):
        img, uv = _frame(20 + i, size)
        truths.append(uv)
        writer.write(cv2.cvtColor(img, cv2.COLOR_GRAY2BGR))
    writer.release()
    src = open_camera(path)
    assert isinstance(src, VideoSource)
    with src:
        frames = list(src)
    assert len(frames) == 5
    assert frames[0].image.shape[:2] == (120, 160)
    assert np.all(np.diff([f.t_ns for f in frames]) > 0)
    assert frames[1].t_ns == pytest.approx(40e6, abs=1e6)
    for f, uv in zip(frames, truths, strict=True):
        b = detect(f.image)
        det, _ = match_to_truth(b.uv, uv, max_dist_px=0.3)  # JPEG blurs a little
        assert len(det) == 3


def test_missing_inputs_are_user_errors(tmp_path):
    for make in (lambda: open_camera(tmp_path / "nope.png"),
                 lambda: ImageSource(tmp_path / "nope.png"),
                 lambda: FolderSource(tmp_path / "nope"),
                 lambda: VideoSource(tmp_path / "nope.avi"),
                 lambda: FolderSource(tmp_path)):  # empty folder
        with pytest.raises(UserError):
            make()
    (tmp_path / "fake.mp4").write_bytes(b"\x00" * 100)
    with pytest.raises(UserError):
        VideoSource(tmp_path / "fake.mp4")
    with pytest.raises(UserError, match="device 57"):
        DeviceSource(57)
    with pytest.raises(UserError, match="device 57"):
        open_camera("57")


def test_sim_source_follows_the_simulator_contract(monkeypatch):
    # The adapter alone, against the render_frame contract: (image, uv, visible).
    calls = []
    cam = Camera("cam3", (200, 150), 180.0, 180.0, 99.5, 74.5, 0.0, np.zeros(5),
                 np.zeros(3), np.array([0.0, 0.0, 2.0]))

    def render_frame(camera, xyz, seed=0, **kwargs):
        calls.append((camera.name, seed, kwargs))
        uv, front = camera.project(xyz)
        visible = front & camera.in_image(uv, 5.0)
        img = render_spots(camera.size, uv[visible], 3.0, rng=seed)
        return img, uv, visible

    monkeypatch.setattr(frames_module, "render_frame", render_frame)
    xyz = np.array([[0.0, 0.0, 0.0], [0.2, 0.1, 0.0], [5.0, 0.0, 0.0]])  # the last is outside
    src = SimSource(cam, xyz, n_frames=3, fps=100.0, seed=7, noise_sigma=1.0)
    frames = list(src)
    assert [f.index for f in frames] == [0, 1, 2]
    assert [f.t_ns for f in frames] == [0, 10_000_000, 20_000_000]
    assert [c[1] for c in calls] == [7, 8, 9] and calls[0][2] == {"noise_sigma": 1.0}
    assert all(f.camera == "cam3" for f in frames)
    assert all(len(src.truth_uv[f.index]) == 2 for f in frames)
    b = detect(frames[0].image)
    det, _ = match_to_truth(b.uv, src.truth_uv[0])
    assert len(det) == 2


def test_sim_source_with_the_simulator():
    from calibkit.synthetic.frames import sim_source

    with pytest.raises(UserError, match="no camera"):
        sim_source(camera="cam42")
    src = sim_source(n_markers=30, n_frames=2, camera="cam1", seed=2)
    frames = list(src)
    assert [f.index for f in frames] == [0, 1] and frames[0].camera == "cam1"
    errors, n_true, n_false = [], 0, 0
    for f in frames:
        assert f.image.dtype == np.uint8 and f.image.shape == (480, 640)
        b = detect(f.image)
        det, tru = match_to_truth(b.uv, src.truth_uv[f.index])
        errors.append(b.uv[det] - src.truth_uv[f.index][tru])
        n_true += len(src.truth_uv[f.index])
        n_false += len(b) - len(det)
        # a marker cut by the image edge may be lost
        assert len(det) >= len(src.truth_uv[f.index]) - 1
    err = np.concatenate(errors)
    assert n_true > 20 and n_false == 0
    # The simulated markers are small (radius ~1 px at 3-5 m) and dim, so 2 DN of noise
    # moves their centroids by ~0.1 px; the truth is the projected marker centre.
    assert np.sqrt((err**2).sum(axis=1).mean()) < 0.2
