"""Frame sources: images, folders, videos, OpenCV camera devices and the simulator, one interface.

Everything that consumes images (detection, the mask builder, the daemon's capture threads)
iterates a source and gets `Frame(camera, index, t_ns, image)`; which kind of camera sits
behind it is decided once, at the edge, by `open_source`. Images come as the file or device
gives them (grayscale or BGR, 8 or 16 bit); the detector converts what it needs.
"""

from __future__ import annotations

import re
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from calibkit.core.errors import UserError

IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm", ".ppm", ".webp"}
VIDEO_SUFFIXES = {".mp4", ".avi", ".mkv", ".mov", ".webm", ".m4v", ".mpg", ".mpeg"}


@dataclass(frozen=True, eq=False)
class Frame:
    """One image from one camera. t_ns: capture time in nanoseconds (monotonic clock for
    live devices, from the frame rate or the container's timestamps for files).

    Cameras whose drivers stamp frames (industrial cameras) also give their own timestamp
    and frame counter: on the camera's clock and from its own start, so they are not
    comparable across cameras until mapped (the daemon learns each camera's offset)."""

    camera: str
    index: int
    t_ns: int
    image: np.ndarray
    device_time_ns: int = -1  # the camera's own timestamp, ns on its clock (-1: none)
    device_frame_id: int = -1  # the camera's own frame counter (-1: none)


class FrameSource:
    """Iterate to get frames; `close()` (or `with`) releases the file or device."""

    camera: str = "cam0"

    def __iter__(self) -> Iterator[Frame]:  # pragma: no cover - every source overrides it
        raise NotImplementedError

    def close(self) -> None:
        pass

    def __enter__(self) -> FrameSource:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _read_image(path: Path) -> np.ndarray:
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise UserError(f"{path} is not an image OpenCV can read")
    if image.ndim == 3 and image.shape[2] == 4:
        image = cv2.cvtColor(image, cv2.COLOR_BGRA2BGR)
    return image


def _natural_key(path: Path) -> list:
    """frame2 before frame10."""
    return [int(p) if p.isdigit() else p for p in re.split(r"(\d+)", path.name)]


class ImageSource(FrameSource):
    """A single image file: one frame."""

    def __init__(self, path: str | Path, camera: str | None = None) -> None:
        self.path = Path(path)
        if not self.path.is_file():
            raise UserError(f"image {self.path} not found")
        self.camera = camera or self.path.stem

    def __iter__(self) -> Iterator[Frame]:
        yield Frame(self.camera, 0, 0, _read_image(self.path))


class FolderSource(FrameSource):
    """The images of a folder in natural name order (frame2 before frame10), at `fps`."""

    def __init__(self, path: str | Path, fps: float = 30.0, camera: str | None = None) -> None:
        self.path = Path(path)
        if not self.path.is_dir():
            raise UserError(f"folder {self.path} not found")
        self.files = sorted((p for p in self.path.iterdir()
                             if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file()),
                            key=_natural_key)
        if not self.files:
            raise UserError(f"folder {self.path} holds no images "
                            f"({', '.join(sorted(IMAGE_SUFFIXES))})")
        if fps <= 0:
            raise UserError(f"fps must be positive, got {fps}")
        self.fps = fps
        self.camera = camera or self.path.name

    def __iter__(self) -> Iterator[Frame]:
        for i, f in enumerate(self.files):
            yield Frame(self.camera, i, round(i * 1e9 / self.fps), _read_image(f))


class _CaptureSource(FrameSource):
    """Shared by video files and devices: an opened cv2.VideoCapture."""

    cap: cv2.VideoCapture | None = None

    def close(self) -> None:
        if self.cap is not None:
            self.cap.release()
            self.cap = None


class VideoSource(_CaptureSource):
    """A video file; timestamps from the container (or the frame rate)."""

    def __init__(self, path: str | Path, camera: str | None = None) -> None:
        self.path = Path(path)
        if not self.path.is_file():
            raise UserError(f"video {self.path} not found")
        self.cap = cv2.VideoCapture(str(self.path))
        if not self.cap.isOpened():
            self.cap = None
            raise UserError(f"{self.path} is not a video OpenCV can read")
        self.fps = self.cap.get(cv2.CAP_PROP_FPS) or 30.0
        self.camera = camera or self.path.stem

    def __iter__(self) -> Iterator[Frame]:
        i = 0
        while self.cap is not None:
            ok, image = self.cap.read()
            if not ok:
                break
            ms = self.cap.get(cv2.CAP_PROP_POS_MSEC)
            t_ns = round(ms * 1e6) if ms > 0 or i == 0 else round(i * 1e9 / self.fps)
            yield Frame(self.camera, i, t_ns, image)
            i += 1


class DeviceSource(_CaptureSource):
    """A live camera through OpenCV (V4L2 on Linux), by device index; stamps frames with
    time.monotonic_ns() as they arrive."""

    def __init__(self, device: int, size: tuple[int, int] | None = None,
                 fps: float | None = None, camera: str | None = None) -> None:
        self.device = int(device)
        self.cap = cv2.VideoCapture(self.device)
        if not self.cap.isOpened():
            self.cap = None
            raise UserError(f"camera device {self.device} could not be opened; check that it "
                            f"is plugged in (ls /dev/video*) and not used by another program")
        if size is not None:
            self.cap.set(cv2.CAP_PROP_FRAME_WIDTH, size[0])
            self.cap.set(cv2.CAP_PROP_FRAME_HEIGHT, size[1])
        if fps is not None:
            self.cap.set(cv2.CAP_PROP_FPS, fps)
        self.camera = camera or f"video{self.device}"

    def __iter__(self) -> Iterator[Frame]:
        i = 0
        while self.cap is not None:
            ok, image = self.cap.read()
            t_ns = time.monotonic_ns()
            if not ok:
                break
            yield Frame(self.camera, i, t_ns, image)
            i += 1


def open_source(spec: str | Path, fps: float = 30.0) -> FrameSource:
    """A source from what a user typed: an image, a folder, a video file or a device index."""
    text = str(spec)
    if re.fullmatch(r"\d+", text):
        return DeviceSource(int(text))
    path = Path(text)
    if path.is_dir():
        return FolderSource(path, fps=fps)
    if not path.exists():
        raise UserError(f"{path} not found (give an image, a folder of images, a video file "
                        f"or a camera device number)")
    suffix = path.suffix.lower()
    if suffix in IMAGE_SUFFIXES:
        return ImageSource(path)
    if suffix in VIDEO_SUFFIXES:
        return VideoSource(path)
    # Unknown suffix: an image if OpenCV reads it as one, else try it as a video.
    if cv2.imread(str(path), cv2.IMREAD_UNCHANGED) is not None:
        return ImageSource(path)
    return VideoSource(path)
