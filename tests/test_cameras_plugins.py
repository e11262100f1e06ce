"""The industrial-camera plugins without a camera: a missing library or producer is one
line; stamps come from grab results and buffers that have the attributes pypylon and
harvesters document; the sources run end to end on stand-in libraries with those APIs.

These stand-ins check our side of the API as documented; they cannot show that a real
camera answers as documented (no camera on the build machine)."""

from __future__ import annotations

import sys
import types

import numpy as np
import pytest

from calibkit.cameras import open_camera
from calibkit.cameras.basler import NO_BLOCK_ID, BlockIds, stamps
from calibkit.cameras.genicam import image_of, producer_file
from calibkit.cameras.genicam import stamps as buffer_stamps
from calibkit.core.errors import UserError


def test_missing_libraries_are_one_line_errors(monkeypatch, calibkit_cli):
    monkeypatch.setitem(sys.modules, "pypylon", None)  # import fails, installed or not
    monkeypatch.setitem(sys.modules, "harvesters", None)
    with pytest.raises(UserError, match=r"need pypylon.*pip install pypylon"):
        open_camera("basler:40012345")
    with pytest.raises(UserError, match=r"need harvesters.*pip install harvesters"):
        open_camera("genicam:")
    r = calibkit_cli("detect", "basler:40012345")
    assert r.code != 0 and len(r.err.strip().splitlines()) == 1 and "pypylon" in r.err


class Result:
    """A pylon grab result: TimeStamp, BlockID, Array, GrabSucceeded(), Release()."""

    def __init__(self, ticks, block, image=None, ok=True):
        self.TimeStamp, self.BlockID, self.ok = ticks, block, ok
        self.Array = image if image is not None else np.zeros((4, 6), np.uint8)
        self.released = False

    def GrabSucceeded(self):  # noqa: N802 - pylon's names
        return self.ok

    def Release(self):  # noqa: N802
        self.released = True


def test_basler_stamps_from_grab_results():
    usb = BlockIds(gige=False)
    assert stamps(Result(123_456_789, 0), 1_000_000_000, usb) == (123_456_789, 0)
    assert stamps(Result(0, 1), 1_000_000_000, usb) == (-1, 1)  # no timestamp
    assert stamps(Result(5, NO_BLOCK_ID), 1_000_000_000, usb) == (5, -1)
    gige = BlockIds(gige=True)
    # a 125 MHz GigE tick clock; 16-bit block ids count 1..65535 and wrap to 1
    ids = [stamps(Result(250_000_000, b), 125_000_000, gige) for b in (65534, 65535, 1, 2)]
    assert ids == [(2_000_000_000, 65534), (2_000_000_000, 65535), (2_000_000_000, 65536),
                   (2_000_000_000, 65537)]
    assert stamps(Result(1, 0), 125_000_000, BlockIds(gige=True))[1] == -1  # 0: no id


class Node:
    """A GenApi node as pypylon wraps it: GetValue/SetValue."""

    def __init__(self, value, limit=None):
        self.value, self.limit = value, limit

    def GetValue(self):  # noqa: N802
        return self.value

    def SetValue(self, value):  # noqa: N802
        self.value = min(value, self.limit) if self.limit is not None else value


def fake_pylon(results, serials=("40012345",), device_class="BaslerUsb", max_fps=None):
    """A pypylon.pylon module with the calls BaslerSource makes; ResultingFrameRate follows
    the rate set, capped at max_fps (as exposure or bandwidth cap a real camera's)."""
    state = {"opened": False, "closed": False, "stopped": False}

    class Info:
        def __init__(self, serial):
            self.serial = serial

        def GetSerialNumber(self):  # noqa: N802
            return self.serial

        def GetDeviceClass(self):  # noqa: N802
            return device_class

    class Camera:
        def __init__(self, device):
            self.device = device
            self.AcquisitionFrameRateEnable = Node(False)
            self.AcquisitionFrameRate = Node(30.0, max_fps)
            self.ExposureAuto = Node("Continuous")
            self.ExposureTime = Node(1000.0)
            self.queue = list(results)
            state["camera"] = self

        @property
        def ResultingFrameRate(self):  # noqa: N802
            return Node(self.AcquisitionFrameRate.value)

        def Open(self):  # noqa: N802
            state["opened"] = True

        def StartGrabbing(self, strategy):  # noqa: N802
            state["strategy"] = strategy

        def IsGrabbing(self):  # noqa: N802
            return bool(self.queue)

        def RetrieveResult(self, timeout_ms, handling):  # noqa: N802
            return self.queue.pop(0)

        def StopGrabbing(self):  # noqa: N802
            state["stopped"] = True

        def Close(self):  # noqa: N802
            state["closed"] = True

    class Factory:
        def EnumerateDevices(self):  # noqa: N802
            return [Info(s) for s in serials]

        def CreateDevice(self, info):  # noqa: N802
            return info

    pylon = types.SimpleNamespace(
        TlFactory=types.SimpleNamespace(GetInstance=Factory), InstantCamera=Camera,
        GrabStrategy_LatestImageOnly="latest", TimeoutHandling_ThrowException="throw")
    return pylon, state


def _install_pylon(monkeypatch, pylon):
    package = types.ModuleType("pypylon")
    package.pylon = pylon
    monkeypatch.setitem(sys.modules, "pypylon", package)
    monkeypatch.setitem(sys.modules, "pypylon.pylon", pylon)


def test_basler_source_on_a_stand_in_pylon(monkeypatch):
    image = np.arange(24, dtype=np.uint8).reshape(4, 6)
    results = [Result(1_000, 0, image), Result(0, 0, ok=False), Result(2_000, 1, image)]
    pylon, state = fake_pylon(results, max_fps=160.0)
    _install_pylon(monkeypatch, pylon)
    said: list[str] = []
    with open_camera("basler:40012345", fps=200, exposure_us=800, name="cam3",
                     warn=said.append) as src:
        frames = list(src)
    cam = state["camera"]
    assert state["opened"] and state["stopped"] and state["closed"]
    assert state["strategy"] == "latest"
    assert cam.AcquisitionFrameRateEnable.value is True and cam.ExposureTime.value == 800.0
    assert cam.ExposureAuto.value == "Off"
    assert src.fps == 160.0 and said == [
        "Basler camera 40012345: asked for 200 fps, it runs at 160 fps (exposure or "
        "bandwidth limit it)"]
    # the failed grab is skipped, and every result is released
    assert [(f.index, f.device_time_ns, f.device_frame_id) for f in frames] == [
        (0, 1_000, 0), (1, 2_000, 1)]
    assert all(r.released for r in results) and frames[0].camera == "cam3"
    assert np.array_equal(frames[0].image, image) and frames[0].image is not image
    assert src.capabilities.device_timestamps and src.capabilities.set_exposure


def test_basler_serial_not_found_lists_the_cameras(monkeypatch):
    pylon, state = fake_pylon([], serials=("111", "222"))
    _install_pylon(monkeypatch, pylon)
    with pytest.raises(UserError, match=r"no Basler camera 999 found \(connected: 111, 222\)"):
        open_camera("basler:999")
    assert "camera" not in state  # nothing was opened


class GenTLBuffer:
    """The GenTL buffer a harvesters Buffer wraps (Buffer.module): frame_id."""

    def __init__(self, frame_id):
        if frame_id is not None:
            self.frame_id = frame_id


class Buffer:
    """A harvesters Buffer: timestamp, timestamp_frequency, module, payload; a context
    manager (leaving it queues the buffer again)."""

    def __init__(self, ticks, hz, frame_id, component=None):
        self._ticks, self.timestamp_frequency = ticks, hz
        self.module = GenTLBuffer(frame_id)
        self.payload = types.SimpleNamespace(components=[component])
        self.queued = False

    @property
    def timestamp(self):
        if self._ticks is None:
            raise RuntimeError("GenTL: not available")  # a producer with no timestamps
        return self._ticks

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.queued = True


def component(image, data_format="Mono8"):
    """A harvesters Component2DImage: data (flat), width, height, num_components_per_pixel,
    data_format."""
    h, w = image.shape[:2]
    n = 1 if image.ndim == 2 else image.shape[2]
    return types.SimpleNamespace(data=image.reshape(-1), width=w, height=h,
                                 num_components_per_pixel=float(n), data_format=data_format)


def test_genicam_stamps_and_images_from_buffers():
    assert buffer_stamps(Buffer(5_000_000_123, 1_000_000_000, 42)) == (5_000_000_123, 42)
    assert buffer_stamps(Buffer(250_000_000, 125_000_000, 7)) == (2_000_000_000, 7)
    assert buffer_stamps(Buffer(None, 1_000_000_000, None)) == (-1, -1)
    assert buffer_stamps(Buffer(0, 1_000_000_000, 3)) == (-1, 3)
    mono = np.arange(12, dtype=np.uint16).reshape(3, 4)
    assert np.array_equal(image_of(component(mono, "Mono12")), mono)
    rgb = np.zeros((2, 3, 3), np.uint8)
    rgb[..., 0] = 255  # red
    bgr = image_of(component(rgb, "RGB8"))
    assert bgr.shape == (2, 3, 3) and (bgr[..., 2] == 255).all() and (bgr[..., 0] == 0).all()
    assert np.array_equal(image_of(component(rgb, "BGR8")), rgb)


def test_genicam_producer_lookup(tmp_path):
    with pytest.raises(UserError, match="set MOCAPD_GENTL_CTI"):
        producer_file({})
    with pytest.raises(UserError, match="no such file"):
        producer_file({"MOCAPD_GENTL_CTI": str(tmp_path / "nope.cti")})
    a, b = tmp_path / "a", tmp_path / "b"
    a.mkdir()
    b.mkdir()
    (b / "z.cti").write_bytes(b"")
    (b / "m.cti").write_bytes(b"")
    env = {"GENICAM_GENTL64_PATH": f"{a}:{tmp_path / 'gone'}:{b}"}
    assert producer_file(env) == str(b / "m.cti")
    assert producer_file({**env, "MOCAPD_GENTL_CTI": str(b / "z.cti")}) == str(b / "z.cti")


def fake_harvesters(buffers, serials=("S1",)):
    """A harvesters.core module with the calls GenICamSource makes."""
    state = {"files": [], "reset": False, "started": False, "destroyed": False}

    class NodeMap:
        def __init__(self):
            self.AcquisitionFrameRate = types.SimpleNamespace(value=30.0)
            self.ExposureTime = types.SimpleNamespace(value=1000.0)

    class Acquirer:
        def __init__(self):
            self.remote_device = types.SimpleNamespace(node_map=NodeMap())
            self.queue = list(buffers)

        def start(self):
            state["started"] = True

        def stop(self):
            state["stopped"] = True

        def destroy(self):
            state["destroyed"] = True

        def fetch(self, timeout=0):
            if not self.queue:
                raise TimeoutError("no buffer within the timeout")
            return self.queue.pop(0)

    class Harvester:
        def __init__(self):
            self.device_info_list = [types.SimpleNamespace(serial_number=s) for s in serials]

        def add_file(self, path):
            state["files"].append(path)

        def update(self):
            pass

        def create(self, key=None):
            if key is not None and key["serial_number"] not in serials:
                raise ValueError("no device found: provide sufficient search key")
            state["acquirer"] = Acquirer()
            return state["acquirer"]

        def reset(self):
            state["reset"] = True

    core = types.ModuleType("harvesters.core")
    core.Harvester = Harvester
    return core, state


def _install_harvesters(monkeypatch, core):
    package = types.ModuleType("harvesters")
    package.core = core
    monkeypatch.setitem(sys.modules, "harvesters", package)
    monkeypatch.setitem(sys.modules, "harvesters.core", core)


def test_genicam_source_on_a_stand_in_harvesters(monkeypatch, tmp_path):
    cti = tmp_path / "maker.cti"
    cti.write_bytes(b"")
    monkeypatch.setenv("MOCAPD_GENTL_CTI", str(cti))
    image = np.arange(12, dtype=np.uint8).reshape(3, 4)
    bufs = [Buffer(1_000, 1_000_000_000, 5, component(image)),
            Buffer(2_000, 1_000_000_000, 6, component(image))]
    core, state = fake_harvesters(bufs)
    _install_harvesters(monkeypatch, core)
    src = open_camera("genicam:S1", fps=100, exposure_us=500)
    frames = []
    with pytest.raises(TimeoutError):  # the camera stops delivering: the error reaches
        for f in src:                  # the reader (the daemon's thread reopens it)
            frames.append(f)
    src.close()
    nodes = state["acquirer"].remote_device.node_map
    assert state["files"] == [str(cti)] and state["started"]
    assert state["destroyed"] and state["reset"]
    assert nodes.AcquisitionFrameRate.value == 100.0 and nodes.ExposureTime.value == 500.0
    assert src.fps == 100.0
    assert [(f.index, f.device_time_ns, f.device_frame_id) for f in frames] == [
        (0, 1_000, 5), (1, 2_000, 6)]
    assert all(b.queued for b in bufs) and np.array_equal(frames[1].image, image)
    with pytest.raises(UserError, match=r"no GenICam camera S9 found .*connected: S1"):
        open_camera("genicam:S9")
