"""A video file as a camera, read through OpenCV; times from the container."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import cv2

from calibkit.cameras.base import Frame, FrameSource
from calibkit.core.errors import UserError

VIDEO_SUFFIXES = {".mp4", ".avi", ".mkv", ".mov", ".webm", ".m4v", ".mpg", ".mpeg"}


class VideoSource(FrameSource):
    """A video file; each frame's time is the container's presentation time (or its index
    over the frame rate where the container gives none)."""

    def __init__(self, path: str | Path, camera: str | None = None) -> None:
        self.path = Path(path)
        if not self.path.is_file():
            raise UserError(f"video {self.path} not found")
        self.cap: cv2.VideoCapture | None = cv2.VideoCapture(str(self.path))
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

    def close(self) -> None:
        if self.cap is not None:
            self.cap.release()
            self.cap = None
