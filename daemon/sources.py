"""Daemon-side blob sources: what each capture thread reads.

A blob source yields CameraSample (one camera's blobs of one frame). Real cameras are
frame sources (calibkit.sources) followed by detection; recordings are played back as they
were captured. The simulated cameras live apart, in daemon.synthetic. Industrial cameras
come from optional plugins; a plugin whose library is missing is reported and skipped.
"""

from __future__ import annotations

import importlib.util
import logging
import time
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from calibkit.camera import Rig
from calibkit.errors import UserError

log = logging.getLogger("mocapd.sources")

PLUGINS = {"basler": "pypylon", "genicam": "harvesters"}


@dataclass(eq=False)
class CameraSample:
    """One camera's blobs of one frame."""

    camera: int
    index: int  # frame number (the same number across cameras when they are triggered)
    t_ns: int  # capture time (monotonic ns)
    arrival_ns: int  # when the daemon got it
    uv: np.ndarray  # (N, 2) distorted pixels
    area: np.ndarray  # (N,)
    peak: np.ndarray  # (N,)
    marker: np.ndarray | None = None  # (N,) true marker ids (simulator only)
    scene_frame: int = -1  # the simulator's frame (truth index)


def missing_plugins(kinds) -> list[str]:
    """The camera plugins asked for whose library is not installed."""
    return [f"{k} (needs {PLUGINS[k]})" for k in kinds
            if k in PLUGINS and importlib.util.find_spec(PLUGINS[k]) is None]


class ReplayScene:
    """A recording (.mcrec or CSV) played back to the daemon, camera by camera.

    The recording's cameras are matched to the rig's by name; frames are taken in order
    at the recording's frame rate (or as fast as the tracker goes)."""

    def __init__(self, path, rig: Rig) -> None:
        from calibkit.recording import load_observations

        obs, _ = load_observations(path)
        index = {n: i for i, n in enumerate(rig.names)}
        unknown = [n for n in obs.camera_names if n not in index]
        if unknown:
            raise UserError(f"{path}: cameras {', '.join(unknown)} are not in the rig "
                            f"({', '.join(rig.names)})")
        self.rig = rig
        self.fps = float(obs.fps or 100.0)
        cam = np.array([index[n] for n in obs.camera_names])[obs.camera]
        self.frame_numbers = np.unique(obs.frame)
        self.n_frames = len(self.frame_numbers)
        if self.n_frames == 0:
            raise UserError(f"{path}: the recording has no frames")
        order = np.lexsort((cam, np.searchsorted(self.frame_numbers, obs.frame)))
        self.obs, self.cam = obs.select(order), cam[order]
        key = np.searchsorted(self.frame_numbers, self.obs.frame) * len(rig) + self.cam
        self.starts = np.searchsorted(key, np.arange(self.n_frames * len(rig) + 1))

    def sample(self, camera: int, i: int, t_ns: int) -> CameraSample:
        k = i * len(self.rig) + camera
        s, e = self.starts[k], self.starts[k + 1]
        o = self.obs
        return CameraSample(camera, i, t_ns, time.monotonic_ns(), o.uv[s:e], o.area[s:e],
                            o.peak[s:e], None if o.marker is None else o.marker[s:e])

    def dropped(self, camera: int, i: int) -> bool:
        return False


def fine_timer_slack() -> None:
    """Let this thread's sleeps end on time (Linux lets a sleep overrun by the thread's
    timer slack, 50 us by default, to batch wake-ups); a simulated camera that wakes late
    would add that to every frame's latency. Best effort: elsewhere it does nothing."""
    try:
        import ctypes

        ctypes.CDLL(None).prctl(29, 1, 0, 0, 0)  # PR_SET_TIMERSLACK: 1 ns
    except (OSError, AttributeError):
        pass


class DetectCamera:
    """A real camera: a calibkit frame source, detection, and undistortion left to the
    tracker (it works in distorted pixels)."""

    def __init__(self, name: str, camera: int, spec: str, detector=None, fps: float = 30.0):
        self.name, self.camera, self.spec, self.fps = name, camera, spec, fps
        self.detector = detector

    def open(self) -> Iterator[CameraSample]:
        from calibkit.detect import DetectorConfig, detect

        source = open_camera(self.spec, self.fps)
        cfg = self.detector or DetectorConfig()
        try:
            for frame in source:
                arrival = time.monotonic_ns()
                blobs = detect(frame.image, cfg)
                yield CameraSample(self.camera, frame.index, frame.t_ns, arrival, blobs.uv,
                                   blobs.area, blobs.peak)
        finally:
            source.close()


def open_camera(spec: str, fps: float):
    """A calibkit frame source for a camera spec; industrial cameras through their plugins."""
    from calibkit.sources import open_source

    kind, _, serial = spec.partition(":")
    if kind == "basler":
        return _PylonSource(serial)
    if kind == "genicam":
        return _HarvesterSource(serial)
    return open_source(spec, fps=fps)


class _PylonSource:
    """A Basler camera through pypylon (untested here: no camera on the build machine)."""

    def __init__(self, serial: str) -> None:
        from pypylon import pylon

        factory = pylon.TlFactory.GetInstance()
        devices = [d for d in factory.EnumerateDevices()
                   if not serial or d.GetSerialNumber() == serial]
        if not devices:
            raise OSError(f"no Basler camera {serial or ''} found")
        self.cam = pylon.InstantCamera(factory.CreateDevice(devices[0]))
        self.cam.Open()
        self.cam.StartGrabbing(pylon.GrabStrategy_LatestImageOnly)
        self.pylon = pylon

    def __iter__(self):
        from calibkit.sources import Frame

        i = 0
        while self.cam.IsGrabbing():
            res = self.cam.RetrieveResult(2000, self.pylon.TimeoutHandling_ThrowException)
            try:
                if res.GrabSucceeded():
                    yield Frame(str(self.cam.GetDeviceInfo().GetSerialNumber()), i,
                                time.monotonic_ns(), res.Array.copy())
                    i += 1
            finally:
                res.Release()

    def close(self) -> None:
        self.cam.Close()


class _HarvesterSource:
    """A GenICam camera through harvesters (untested here: no camera on the build machine).
    MOCAPD_GENTL_CTI names the GenTL producer (.cti) file."""

    def __init__(self, serial: str) -> None:
        import os

        from harvesters.core import Harvester

        self.h = Harvester()
        cti = os.environ.get("MOCAPD_GENTL_CTI")
        if not cti:
            raise OSError("set MOCAPD_GENTL_CTI to your camera's GenTL producer (.cti) file")
        self.h.add_file(cti)
        self.h.update()
        sel = {"serial_number": serial} if serial else 0
        self.ia = self.h.create(sel)
        self.ia.start()

    def __iter__(self):
        from calibkit.sources import Frame

        i = 0
        while True:
            with self.ia.fetch(timeout=2.0) as buf:
                comp = buf.payload.components[0]
                image = comp.data.reshape(comp.height, comp.width).copy()
            yield Frame("genicam", i, time.monotonic_ns(), image)
            i += 1

    def close(self) -> None:
        self.ia.stop()
        self.ia.destroy()
        self.h.reset()
