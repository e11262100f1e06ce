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

from calibkit.core.camera import Rig
from calibkit.core.errors import UserError

log = logging.getLogger("mocapd.sources")

PLUGINS = {"basler": "pypylon", "genicam": "harvesters"}


@dataclass(eq=False)
class CameraSample:
    """One camera's blobs of one frame, with what the camera said about when it took it.

    Real cameras open at different moments and count frames from their own start, and
    those that stamp frames do it on their own clocks; so frames are paired by time, not
    by counter: the multiplexer maps `device_time_ns` (or `device_frame_id`) to the
    daemon's clock (daemon.clocks) and writes the result into `t_ns`.
    """

    camera: int
    index: int  # the source's count of frames since it opened (restarts when it reopens)
    t_ns: int  # capture time on the daemon's clock (monotonic ns): the source's estimate,
    # refined by the multiplexer from the device's own time
    arrival_ns: int  # when the daemon got it
    uv: np.ndarray  # (N, 2) distorted pixels
    area: np.ndarray  # (N,)
    peak: np.ndarray  # (N,)
    device_time_ns: int = -1  # the camera's own timestamp, ns on its own clock (-1: none)
    device_frame_id: int = -1  # the camera's own frame counter (-1: none)


def missing_plugins(kinds) -> list[str]:
    """The camera plugins asked for whose library is not installed."""
    return [f"{k} (needs {PLUGINS[k]})" for k in kinds
            if k in PLUGINS and importlib.util.find_spec(PLUGINS[k]) is None]


class ReplayScene:
    """A recording (.mcrec or CSV) played back to the daemon, camera by camera.

    The recording's cameras are matched to the rig's by name; frames are taken in order
    at the recording's frame rate (or as fast as the tracker goes)."""

    def __init__(self, path, rig: Rig) -> None:
        from calibkit.core.recording import load_observations

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
                            o.peak[s:e])

    def dropped(self, camera: int, i: int) -> bool:
        return False


class ReplayCamera:
    """One camera of a recording as a capture thread reads it: paced at the recording's
    rate from a shared start, frame i of every camera at the same time (the recording's
    frames are already paired). The replay ends with its recording."""

    def __init__(self, scene: ReplayScene, camera: int, t0_ns: int) -> None:
        self.scene, self.camera, self.t0_ns = scene, camera, t0_ns
        self.name = scene.rig.names[camera]

    def open(self) -> Iterator[CameraSample]:
        fine_timer_slack()
        period = 1e9 / self.scene.fps
        i = max(0, int(np.ceil((time.monotonic_ns() - self.t0_ns) / period)))
        while i < self.scene.n_frames:
            due = self.t0_ns + round(i * period)
            wait = due - time.monotonic_ns()
            if wait > 0:
                time.sleep(wait * 1e-9)
            yield self.scene.sample(self.camera, i, due)
            i += 1


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

    def __init__(self, name: str, camera: int, spec: str, detector=None, fps: float = 30.0,
                 device_stamps: bool = True):
        self.name, self.camera, self.spec, self.fps = name, camera, spec, fps
        self.detector = detector
        self.device_stamps = device_stamps  # False: pair by arrival (stamps not trusted)

    def open(self) -> Iterator[CameraSample]:
        from calibkit.vision.detect import DetectorConfig, detect

        source = open_camera(self.spec, self.fps)
        default = DetectorConfig()
        try:
            for frame in source:
                arrival = time.monotonic_ns()
                # read each frame: a reload (or the live view) swaps in new settings
                blobs = detect(frame.image, self.detector or default)
                # a frame stamped by the camera: its time is on the camera's clock, and the
                # multiplexer maps it; otherwise the source's time (a live device's read time,
                # a file's own timeline)
                stamped = self.device_stamps and (frame.device_time_ns >= 0
                                                  or frame.device_frame_id >= 0)
                if not stamped:
                    yield CameraSample(self.camera, frame.index, frame.t_ns, arrival, blobs.uv,
                                       blobs.area, blobs.peak)
                    continue
                yield CameraSample(self.camera, frame.index, arrival, arrival, blobs.uv,
                                   blobs.area, blobs.peak, frame.device_time_ns,
                                   frame.device_frame_id)
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
    """A Basler camera through pypylon (untested here: no camera on the build machine).

    Each frame carries the camera's own timestamp and frame counter, as pylon documents
    them: the grab result's TimeStamp is the camera's tick count when the frame was taken
    (ticks since it powered up or was reset; 1 ns on USB3 cameras, GevTimestampTickFrequency
    per second on GigE ones) and BlockID its frame counter (USB3: from 0; GigE: from 1,
    wrapping after 65535 unless extended ids are on, 0 when unsupported)."""

    def __init__(self, serial: str) -> None:
        from pypylon import pylon

        factory = pylon.TlFactory.GetInstance()
        devices = [d for d in factory.EnumerateDevices()
                   if not serial or d.GetSerialNumber() == serial]
        if not devices:
            raise OSError(f"no Basler camera {serial or ''} found")
        self.cam = pylon.InstantCamera(factory.CreateDevice(devices[0]))
        self.cam.Open()
        self.gige = "GigE" in str(devices[0].GetDeviceClass())
        self.tick_hz = 1_000_000_000
        if self.gige:
            try:
                self.tick_hz = int(self.cam.GevTimestampTickFrequency.GetValue())
            except Exception:  # noqa: BLE001 - a model without the node: ns ticks
                pass
        self.cam.StartGrabbing(pylon.GrabStrategy_LatestImageOnly)
        self.pylon = pylon
        self._last_block = -1
        self._wraps = 0

    def _frame_id(self, block: int) -> int:
        """The block id as a counter that never wraps (-1: the camera gives none)."""
        if block >= 2**64 - 1 or (self.gige and block == 0):
            return -1
        if self.gige and 0 <= block < self._last_block - 32768:
            self._wraps += 1  # 16-bit GigE block ids go 65535 -> 1
        self._last_block = block
        return block + 65535 * self._wraps

    def __iter__(self):
        from calibkit.sources import Frame

        i = 0
        serial = str(self.cam.GetDeviceInfo().GetSerialNumber())
        while self.cam.IsGrabbing():
            res = self.cam.RetrieveResult(2000, self.pylon.TimeoutHandling_ThrowException)
            try:
                if res.GrabSucceeded():
                    arrival = time.monotonic_ns()
                    ticks = int(res.TimeStamp)
                    device_ns = ticks * 1_000_000_000 // self.tick_hz if ticks > 0 else -1
                    yield Frame(serial, i, arrival, res.Array.copy(), device_ns,
                                self._frame_id(int(res.BlockID)))
                    i += 1
            finally:
                res.Release()

    def close(self) -> None:
        self.cam.Close()


class _HarvesterSource:
    """A GenICam camera through harvesters (untested here: no camera on the build machine).
    MOCAPD_GENTL_CTI names the GenTL producer (.cti) file.

    Each frame carries the camera's own timestamp and frame id as harvesters documents
    them: Buffer.timestamp_ns (ns on the device's clock; producers that cannot convert
    raise, and then Buffer.timestamp counts Buffer.timestamp_frequency ticks per second)
    and the GenTL buffer's frame id (BUFFER_INFO_FRAMEID)."""

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

    @staticmethod
    def _stamps(buf) -> tuple[int, int]:
        """(device time ns, frame id) of a harvesters Buffer; -1 for what it lacks."""
        device_ns = -1
        try:
            device_ns = int(buf.timestamp_ns)
        except Exception:  # noqa: BLE001 - the producer has no ns timestamps
            try:
                hz = int(buf.timestamp_frequency)
                ticks = int(buf.timestamp)
                if hz > 0 and ticks > 0:
                    device_ns = ticks * 1_000_000_000 // hz
            except Exception:  # noqa: BLE001 - nor ticks
                pass
        try:
            frame_id = int(buf._buffer.frame_id)  # the wrapped GenTL buffer's frame id
        except Exception:  # noqa: BLE001
            frame_id = -1
        return (device_ns if device_ns > 0 else -1), frame_id

    def __iter__(self):
        from calibkit.sources import Frame

        i = 0
        while True:
            with self.ia.fetch(timeout=2.0) as buf:
                arrival = time.monotonic_ns()
                device_ns, frame_id = self._stamps(buf)
                comp = buf.payload.components[0]
                image = comp.data.reshape(comp.height, comp.width).copy()
            yield Frame("genicam", i, arrival, image, device_ns, frame_id)
            i += 1

    def close(self) -> None:
        self.ia.stop()
        self.ia.destroy()
        self.h.reset()
