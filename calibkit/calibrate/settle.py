"""Settle detection: after a display (monitor or projector) changes its pattern, which camera
frames show the new pattern fully?

Display and camera latencies differ per setup (a monitor's input lag, a projector's frame
buffer, a webcam's internal queue) from one to several frames, and a frame exposed across
the switch shows a blend of both patterns. So we do not guess a delay: each frame is reduced
to a coarse signature (block means, which average the sensor noise away) and the image is
settled once it has moved away from the previous pattern's signature and then stopped
changing for `hold` consecutive frames. A change that shows nothing in this camera (a dot
outside its view) is settled by timeout after the latency measured on earlier changes.

The detector is fed frames one at a time (`feed`), so live capture, recordings and the
simulator share it; nothing here assumes a monitor.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from calibkit.vision.gray import to_gray


def signature(image: np.ndarray, block_px: int = 8) -> np.ndarray:
    """Block means of a grayscale (or BGR) image, float32: noise / block_px, detail kept."""
    img = to_gray(image, np.float32)
    h, w = img.shape[:2]
    return cv2.resize(img, (max(1, w // block_px), max(1, h // block_px)),
                      interpolation=cv2.INTER_AREA)


def signature_noise(images: list[np.ndarray], block_px: int = 8) -> float:
    """Largest block difference between consecutive frames of a static scene: the level of
    change that means nothing (use a few frames of one held pattern)."""
    sigs = [signature(im, block_px) for im in images]
    if len(sigs) < 2:
        return 0.0
    steps = [np.max(np.abs(b - a)) for a, b in zip(sigs[:-1], sigs[1:], strict=True)]
    return float(np.median(steps))


@dataclass
class SettleDetector:
    """Feed every camera frame after each pattern change; `feed` says when it has settled.

    noise: block-difference level of a static scene (signature_noise); k: how many times
    the noise a real change must exceed; hold: consecutive still frames needed;
    max_wait_frames: give up waiting for a change after this many frames when no latency
    has been learnt yet.
    """

    noise: float = 1.0
    k: float = 4.0
    hold: int = 2
    block_px: int = 8
    max_wait_frames: int = 30
    latencies: list[int] = field(default_factory=list)
    _reference: np.ndarray | None = None
    _last: np.ndarray | None = None
    _frames: int = 0
    _changed_at: int = -1
    _still: int = 0

    @property
    def threshold(self) -> float:
        return self.k * max(self.noise, 0.25)

    @property
    def latency_frames(self) -> int | None:
        """Median frames from a pattern change to the first changed camera frame."""
        return int(np.median(self.latencies)) if self.latencies else None

    def start(self, image: np.ndarray | None = None, expect_change: bool = True) -> None:
        """A new pattern was just requested. `image` (optional): the last frame of the old
        pattern, if not already fed. With expect_change=False, settle as soon as the image
        stops changing (after the user moved the target, before the first pattern)."""
        if image is not None:
            self._last = signature(image, self.block_px)
        self._reference = self._last
        self._frames = 0
        self._changed_at = -1 if expect_change else 0
        self._still = 0

    def feed(self, image: np.ndarray) -> bool:
        """One frame taken after `start()`; True once the new pattern is settled (and for
        each further frame that stays still)."""
        sig = signature(image, self.block_px)
        prev, self._last = self._last, sig
        self._frames += 1
        thr = self.threshold
        if self._reference is None:  # nothing to compare with: the first pattern
            self._reference = sig
            self._changed_at = 0
        if self._changed_at < 0:
            if np.max(np.abs(sig - self._reference)) > thr:
                self._changed_at = self._frames
                self.latencies.append(self._frames)
                self._still = 0
                return False
            # no change yet: either still in the latency, or nothing visible changed
            wait = (self.max_wait_frames if self.latency_frames is None
                    else self.latency_frames + self.hold + 1)
            if self._frames >= wait:
                self._changed_at = self._frames
            return self._frames > wait
        still = prev is not None and np.max(np.abs(sig - prev)) <= thr
        self._still = self._still + 1 if still else 0
        return self._still >= self.hold
