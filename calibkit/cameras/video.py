"""A video file as a camera, read through OpenCV; times from the container."""

from __future__ import annotations

from pathlib import Path

import cv2

from calibkit.cameras.base import CaptureSource
from calibkit.core.errors import UserError

VIDEO_SUFFIXES = {".mp4", ".avi", ".mkv", ".mov", ".webm", ".m4v", ".mpg", ".mpeg"}


class VideoSource(CaptureSource):
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

    def _time_ns(self, index: int) -> int:
        ms = self.cap.get(cv2.CAP_PROP_POS_MSEC)
        return round(ms * 1e6) if ms > 0 or index == 0 else round(index * 1e9 / self.fps)
