"""The one camera interface: a frame source yields Frames, says what it can do, and closes.

Every consumer of images (detection, the mask builder, the calibration captures, the
daemon's capture threads) iterates a source and gets `Frame(camera, index, t_ns, image)`;
which kind of camera sits behind it (a file, an OpenCV device, an industrial camera, the
simulator) is decided once, at the edge, by `calibkit.cameras.open_camera`. Images come as
the file or device gives them (grayscale or BGR, 8 or 16 bit); the detector converts what
it needs.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np

# Called with a line the user should read about how a camera was opened (a frame rate the
# device would not take); the calibration commands print it, the daemon logs it.
Warn = Callable[[str], None]


@dataclass(frozen=True, eq=False)
class Frame:
    """One image from one camera. t_ns: capture time in nanoseconds (monotonic clock for
    live devices, from the frame rate or the container's timestamps for files); index: the
    source's count of frames since it opened.

    Cameras whose drivers stamp frames (industrial cameras) also give their own timestamp
    and frame counter: on the camera's clock and from its own start, so they are not
    comparable across cameras until mapped (the daemon learns each camera's offset)."""

    camera: str
    index: int
    t_ns: int
    image: np.ndarray
    device_time_ns: int = -1  # the camera's own timestamp, ns on its clock (-1: none)
    device_frame_id: int = -1  # the camera's own frame counter (-1: none)


@dataclass(frozen=True)
class Capabilities:
    """What a kind of camera gives and takes, so callers can decide without knowing it.

    live: a running camera (frames not read are lost; it never ends by itself), as opposed
    to a file read at will. device_timestamps / device_frame_ids: frames carry the camera's
    own time / counter (Frame.device_time_ns, device_frame_id). set_fps: a frame rate asked
    for is applied (a device's rate, or an image folder's timeline). set_exposure: an
    exposure time asked for is applied. set_size: an image size asked for is applied."""

    live: bool = False
    device_timestamps: bool = False
    device_frame_ids: bool = False
    set_fps: bool = False
    set_exposure: bool = False
    set_size: bool = False


class FrameSource:
    """Iterate to get frames; `close()` (or `with`) releases the file or device.

    `camera` names the camera (it goes into every Frame); `fps` is the rate the source says
    its frames come at (None: it does not know); `capabilities` says what it supports.
    Opening happens in the constructor (through `open_camera`), so a source that exists is
    open: a missing file, device or library is a UserError there, not at the first frame."""

    camera: str = "cam0"
    fps: float | None = None
    capabilities: Capabilities = Capabilities()

    def __iter__(self) -> Iterator[Frame]:  # pragma: no cover - every source overrides it
        raise NotImplementedError

    def close(self) -> None:
        pass

    def __enter__(self) -> FrameSource:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class CaptureSource(FrameSource):
    """A source read through an OpenCV VideoCapture (`self.cap`; None once closed): read
    until it ends, each frame stamped by `_time_ns(index)` right after it is read."""

    cap = None

    def _time_ns(self, index: int) -> int:  # pragma: no cover - every capture overrides it
        raise NotImplementedError

    def __iter__(self) -> Iterator[Frame]:
        i = 0
        while self.cap is not None:
            ok, image = self.cap.read()
            t_ns = self._time_ns(i)
            if not ok:
                break
            yield Frame(self.camera, i, t_ns, image)
            i += 1

    def close(self) -> None:
        if self.cap is not None:
            self.cap.release()
            self.cap = None


def rate_differs(asked: float, got: float) -> bool:
    """Whether a device's read-back frame rate is not the one asked for (within 1 %, as
    drivers round: 29.97 for 30)."""
    return not got > 0 or abs(got - asked) > 0.01 * asked
