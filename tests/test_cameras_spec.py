"""Camera specs name the right kind; a frame rate asked of an OpenCV device is set, read
back and reported when the device runs at another; the daemon's `[[camera]] fps` gets there."""

from __future__ import annotations

import logging

import cv2
import numpy as np
import pytest

from calibkit.cameras import CameraSpec, missing_plugins, open_camera, parse_spec
from calibkit.core.errors import UserError


def _png(path, value=40):
    cv2.imwrite(str(path), np.full((12, 16), value, np.uint8))


def test_specs_name_their_kind(tmp_path):
    _png(tmp_path / "shot.png")
    (tmp_path / "frames").mkdir()
    _png(tmp_path / "frames" / "0.png")
    (tmp_path / "odd:name").mkdir()  # a folder whose name has a colon is still a folder
    _png(tmp_path / "still.png")
    (tmp_path / "still.png").rename(tmp_path / "still.dat")  # an image under an odd suffix
    (tmp_path / "clip.avi").write_bytes(b"\x00")  # by suffix: not opened while parsing
    cases = {
        "0": CameraSpec("device", "0"), " 12 ": CameraSpec("device", "12"),
        "/dev/video3": CameraSpec("device", "3"),
        "basler:40012345": CameraSpec("basler", "40012345"), "basler:": CameraSpec("basler", ""),
        "GenICam:ABC-1": CameraSpec("genicam", "ABC-1"),
        str(tmp_path / "shot.png"): CameraSpec("image", str(tmp_path / "shot.png")),
        str(tmp_path / "frames"): CameraSpec("folder", str(tmp_path / "frames")),
        str(tmp_path / "odd:name"): CameraSpec("folder", str(tmp_path / "odd:name")),
        str(tmp_path / "still.dat"): CameraSpec("image", str(tmp_path / "still.dat")),
        str(tmp_path / "clip.avi"): CameraSpec("video", str(tmp_path / "clip.avi")),
    }
    for spec, kind in cases.items():
        assert parse_spec(spec) == kind, spec
    for bad, says in (("", "empty"), ("zenoh:cam0", "unknown camera kind 'zenoh'"),
                      (str(tmp_path / "nope.png"), "not found")):
        with pytest.raises(UserError, match=says):
            parse_spec(bad)


def test_what_each_file_kind_supports(tmp_path):
    _png(tmp_path / "shot.png")
    folder = open_camera(tmp_path, fps=50.0, name="left")
    assert folder.capabilities.set_fps and not folder.capabilities.live
    assert folder.camera == "left" and folder.fps == 50.0
    assert [f.t_ns for f in folder] == [0]
    image = open_camera(tmp_path / "shot.png")
    assert not image.capabilities.set_fps and not image.capabilities.device_timestamps
    assert not image.capabilities.set_exposure
    with pytest.raises(UserError, match="cannot set the exposure"):
        open_camera(tmp_path, exposure_us=500.0)
    assert missing_plugins(["image", "device"]) == []


class FakeCapture:
    """cv2.VideoCapture as a V4L2 device answers: it opens by number, takes a frame size,
    and runs at `modes` rates only (a rate it lacks is rounded to its nearest one, as
    drivers do); reads give 3 frames."""

    modes = (30.0,)
    opened: list[FakeCapture] = []

    def __init__(self, index):
        self.index = index
        self.props = {cv2.CAP_PROP_FPS: self.modes[0], cv2.CAP_PROP_FRAME_WIDTH: 640.0,
                      cv2.CAP_PROP_FRAME_HEIGHT: 480.0}
        self.sets: list[tuple[int, float]] = []
        self.left = 3
        self.released = False
        FakeCapture.opened.append(self)

    def isOpened(self):  # noqa: N802 - OpenCV's name
        return True

    def set(self, prop, value):
        self.sets.append((prop, value))
        if prop == cv2.CAP_PROP_FPS:
            value = min(self.modes, key=lambda m: abs(m - value))
        self.props[prop] = float(value)
        return True

    def get(self, prop):
        return self.props.get(prop, 0.0)

    def read(self):
        if self.left == 0:
            return False, None
        self.left -= 1
        return True, np.zeros((int(self.props[cv2.CAP_PROP_FRAME_HEIGHT]),
                               int(self.props[cv2.CAP_PROP_FRAME_WIDTH]), 3), np.uint8)

    def release(self):
        self.released = True


@pytest.fixture
def capture(monkeypatch):
    FakeCapture.opened = []
    FakeCapture.modes = (30.0,)
    monkeypatch.setattr(cv2, "VideoCapture", FakeCapture)
    return FakeCapture


def test_device_fps_is_set_read_back_and_reported(capture):
    said: list[str] = []
    with open_camera("2", fps=120, size=(320, 240), name="cam0", warn=said.append) as src:
        frames = list(src)
    (cap,) = capture.opened
    assert cap.index == 2 and cap.released
    assert (cv2.CAP_PROP_FPS, 120.0) in cap.sets
    # the size goes first: a device's rates depend on its mode
    assert [p for p, _ in cap.sets] == [cv2.CAP_PROP_FRAME_WIDTH, cv2.CAP_PROP_FRAME_HEIGHT,
                                        cv2.CAP_PROP_FPS]
    assert src.fps == 30.0  # what the device runs at, not what was asked
    assert said == ["camera cam0 (device 2): asked for 120 fps, the device reports 30 fps"]
    assert [f.index for f in frames] == [0, 1, 2] and frames[0].image.shape == (240, 320, 3)
    assert all(f.camera == "cam0" and f.device_time_ns == -1 for f in frames)
    assert src.capabilities.live and src.capabilities.set_fps
    assert not src.capabilities.device_timestamps


def test_device_fps_taken_or_not_asked_is_not_reported(capture):
    capture.modes = (30.0, 60.0, 120.0)
    said: list[str] = []
    src = open_camera("0", fps=120, warn=said.append)
    assert src.fps == 120.0 and said == []
    src.close()
    src = open_camera("0", warn=said.append)  # no rate asked: the device keeps its own
    assert not any(p == cv2.CAP_PROP_FPS for p, _ in capture.opened[-1].sets)
    assert src.fps == 30.0 and said == []
    src.close()
    with pytest.raises(UserError, match="fps must be positive"):
        open_camera("0", fps=0)


def test_daemon_camera_fps_reaches_the_device(capture, tmp_path, caplog, monkeypatch):
    """`[[camera]] fps` goes from the configuration through the daemon's capture source to
    the device; the device's refusal is logged by the daemon. Without it, nothing is set."""
    from calibkit.synthetic import sim
    from daemon.config.mocapd import parse_config
    from daemon.service.daemon import Daemon

    sim.make_rig(2, 4.0, seed=1).save(tmp_path / "rig.toml")
    cfg = parse_config({"rig": "rig.toml", "camera": [
        {"name": "cam0", "source": "0", "fps": 90},
        {"name": "cam1", "source": "1"}]}, base=tmp_path)
    assert [c.fps for c in cfg.cameras] == [90.0, None]
    cams = Daemon(cfg)._cameras(cfg)
    # the daemon's logger does not propagate once set up (daemon.process.logs): listen on it alone
    daemon_log = logging.getLogger("mocapd")
    monkeypatch.setattr(daemon_log, "handlers", [caplog.handler])
    monkeypatch.setattr(daemon_log, "propagate", False)
    samples = [list(c.open()) for c in cams]
    assert [len(s) for s in samples] == [3, 3]
    c0, c1 = capture.opened
    assert (cv2.CAP_PROP_FPS, 90.0) in c0.sets
    assert not any(p == cv2.CAP_PROP_FPS for p, _ in c1.sets)
    warned = [r for r in caplog.records if r.name == "mocapd.sources"]
    assert [r.getMessage() for r in warned] == [
        "camera cam0 (device 0): asked for 90 fps, the device reports 30 fps"]


def test_capture_sources_share_one_shape(tmp_path):
    """The daemon's capture threads read every kind the same way
    (daemon.capture.sources.BlobSource): live cameras, recordings and the simulator."""
    from calibkit.core.observations import Observations
    from calibkit.core.recording import save_observations
    from calibkit.synthetic import sim
    from daemon.capture.sources import BlobSource, DetectCamera, ReplayCamera, ReplayScene
    from daemon.config.mocapd import SimConfig
    from daemon.synthetic.scene import SimCamera, SimScene

    rig = sim.make_rig(2, 4.0, seed=1)
    obs = Observations(rig.names, [c.size for c in rig], np.array([0, 0]), np.array([0, 1]),
                       np.array([0, 0]), np.full((2, 2), 100.0), np.ones(2), np.ones(2))
    save_observations(tmp_path / "r.mcrec", obs)
    kinds = [DetectCamera("cam0", 0, "0"),
             ReplayCamera(ReplayScene(tmp_path / "r.mcrec", rig), 0, 0),
             SimCamera(SimScene(SimConfig(cameras=2), n_frames=2), 1, 0)]
    assert all(isinstance(k, BlobSource) for k in kinds)
    assert [k.camera for k in kinds] == [0, 0, 1]
