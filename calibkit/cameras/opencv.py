"""A live camera through OpenCV (V4L2 on Linux, by device number): webcams and USB cameras.

A frame rate or size asked for is set on the device, then read back: drivers round a rate
to the nearest mode they have, or ignore it, and the user is told when what the device
reports is not what was asked (the capture's timing and exposure depend on it).
"""

from __future__ import annotations

import logging
import time

import cv2

from calibkit.cameras.base import Capabilities, CaptureSource, Warn, rate_differs
from calibkit.core.errors import UserError

log = logging.getLogger("calibkit.cameras")


class DeviceSource(CaptureSource):
    """An OpenCV capture device, stamped with time.monotonic_ns() as each frame is read
    (OpenCV gives no device timestamp or counter)."""

    capabilities = Capabilities(live=True, set_fps=True, set_size=True)

    def __init__(self, device: int, size: tuple[int, int] | None = None,
                 fps: float | None = None, camera: str | None = None,
                 warn: Warn | None = None) -> None:
        self.device = int(device)
        self.camera = camera or f"video{self.device}"
        warn = warn or log.warning
        if fps is not None and not fps > 0:
            raise UserError(f"fps must be positive, got {fps}")
        self.cap: cv2.VideoCapture | None = cv2.VideoCapture(self.device)
        if not self.cap.isOpened():
            self.cap = None
            raise UserError(f"camera device {self.device} could not be opened; check that it "
                            f"is plugged in (ls /dev/video*) and not used by another program")
        if size is not None:  # before the rate: a device's rates depend on its image size
            self.cap.set(cv2.CAP_PROP_FRAME_WIDTH, size[0])
            self.cap.set(cv2.CAP_PROP_FRAME_HEIGHT, size[1])
            got_size = (int(self.cap.get(cv2.CAP_PROP_FRAME_WIDTH)),
                        int(self.cap.get(cv2.CAP_PROP_FRAME_HEIGHT)))
            if got_size != tuple(size):
                warn(f"camera {self.camera} (device {self.device}): asked for "
                     f"{size[0]}x{size[1]}, the device gives {got_size[0]}x{got_size[1]}")
        if fps is not None:
            self.cap.set(cv2.CAP_PROP_FPS, float(fps))
        got = float(self.cap.get(cv2.CAP_PROP_FPS) or 0.0)
        self.fps = got if got > 0 else None
        if fps is not None and rate_differs(fps, got):
            said = f"reports {got:g} fps" if got > 0 else "reports no frame rate"
            warn(f"camera {self.camera} (device {self.device}): asked for {fps:g} fps, the "
                 f"device {said}")

    def _time_ns(self, index: int) -> int:
        return time.monotonic_ns()
