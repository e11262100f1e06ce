"""Daemon-side blob sources: what each capture thread reads.

A blob source has `name` (the rig's camera name), `camera` (its index in the rig) and
`open()`, which yields CameraSample (one camera's blobs of one frame) until the camera
fails (the capture thread reopens it) or ends. Real cameras are calibkit cameras
(calibkit.cameras: OpenCV devices, files, Basler, GenICam) followed by detection
(DetectCamera); recordings are played back as they were captured (ReplayCamera); the
simulated cameras live apart, in daemon.synthetic, and have the same shape.
"""

from __future__ import annotations

import ctypes
import logging
import time
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np

from calibkit import cameras
from calibkit.core.camera import Rig
from calibkit.core.errors import UserError
from calibkit.core.pairing import pair_frames
from calibkit.core.recording import load_observations
from calibkit.vision.detect import DetectorConfig, detect

log = logging.getLogger("mocapd.sources")


@dataclass(eq=False)
class CameraSample:
    """One camera's blobs of one frame, with what the camera said about when it took it.

    Real cameras open at different moments and count frames from their own start, and
    those that stamp frames do it on their own clocks; so frames are paired by time, not
    by counter: the multiplexer maps `device_time_ns` (or `device_frame_id`) to the
    daemon's clock (daemon.capture.clocks) and writes the result into `t_ns`.
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


@runtime_checkable
class BlobSource(Protocol):
    """What a capture thread reads: DetectCamera, ReplayCamera and daemon.synthetic's
    SimCamera. `open()` starts a session (the thread calls it again after a failure)."""

    name: str  # the rig's name for the camera
    camera: int  # its index in the rig

    def open(self) -> Iterator[CameraSample]: ...


class ReplayScene:
    """A recording (.mcrec or CSV) played back to the daemon, camera by camera.

    The recording's cameras are matched to the rig's by name; frames are taken in order
    at the recording's frame rate (or as fast as the tracker goes). A recording of each
    camera's own frames (a calibkit wand capture) is paired by capture time first
    (calibkit.core.pairing); one numbered by instant (mocapd's) is played as it is."""

    def __init__(self, path, rig: Rig) -> None:
        obs = pair_frames(load_observations(path)[0]).obs
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
        ctypes.CDLL(None).prctl(29, 1, 0, 0, 0)  # PR_SET_TIMERSLACK: 1 ns
    except (OSError, AttributeError):
        pass


class DetectCamera:
    """A real camera: a calibkit camera (calibkit.cameras), detection, and undistortion
    left to the tracker (it works in distorted pixels). fps: the rate to run the camera at
    (None: its own); a device that will not take it is logged."""

    def __init__(self, name: str, camera: int, spec: str, detector=None,
                 fps: float | None = None, device_stamps: bool = True):
        self.name, self.camera, self.spec, self.fps = name, camera, spec, fps
        self.detector = detector
        self.device_stamps = device_stamps  # False: pair by arrival (stamps not trusted)

    def open(self) -> Iterator[CameraSample]:
        source = open_camera(self.spec, self.fps, self.name)
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


def open_camera(spec: str, fps: float | None = None,
                name: str | None = None) -> cameras.FrameSource:
    """The frame source for a `[[camera]] source` spec: calibkit's kinds (calibkit.cameras);
    a setting the camera does not take is logged here."""
    return cameras.open_camera(spec, fps=fps, name=name, warn=log.warning)
