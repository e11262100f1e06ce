"""Capturing a dot schedule with one camera: show, wait to settle, average, detect, decode.

For each frame of a schedule (projector.patterns) the display is asked to show it; camera
frames are fed to a SettleDetector until the image has settled; then `samples` frames are
averaged. Dots are detected on (all-on - all-off) of each layer, which removes the screen's
glow and any room light; each dot's position is also measured in every single all-on
sample, and dots whose scatter is large (the monitor or camera moved, motion blur) are
dropped. The decoder then names each dot. The result is a table of (point id, image
position, scatter) per view.

`DotDevice` is all this needs from hardware: `show(dots)` and `grab() -> image`. A monitor
and a webcam, a projector and one camera of a rig, or the simulator all fit.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import cv2
import numpy as np

from calibkit.detect import DetectorConfig, detect
from calibkit.errors import UserError
from calibkit.settle import SettleDetector, signature_noise
from projector.display import Dots
from projector.patterns import (
    ROLE_ON,
    Schedule,
    name_layers,
)


class DotDevice(Protocol):
    def show(self, dots: Dots) -> None: ...

    def grab(self) -> np.ndarray: ...


@dataclass(frozen=True, eq=False)
class DotView:
    """Identified dots of one view: global point ids (N,), image positions (N, 2) px,
    position scatter over the samples (N,) px; frames: camera frames the view took;
    dot_radius_px: the dots' typical apparent radius in the image (from their area above
    the detection threshold, so it includes the blur's skirt)."""

    ids: np.ndarray
    uv: np.ndarray
    scatter_px: np.ndarray
    frames: int
    rejected: int = 0
    dot_radius_px: float = float("nan")
    moved: int = 0  # dots dropped because they moved between the samples

    def __len__(self) -> int:
        return len(self.ids)


def _gray(image: np.ndarray) -> np.ndarray:
    img = np.asarray(image)
    if img.ndim == 3:
        img = cv2.cvtColor(img[:, :, :3], cv2.COLOR_BGR2GRAY)
    return img.astype(np.float32)


def _nearest(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For each row of a: index of the nearest row of b and its distance (b may be empty)."""
    if len(b) == 0:
        return np.zeros(len(a), np.int64), np.full(len(a), np.inf)
    from scipy.spatial import cKDTree

    d, i = cKDTree(b).query(a)
    return np.asarray(i, np.int64), np.asarray(d, np.float64)


@dataclass
class DotCapture:
    """Runs a schedule on a device. samples: frames averaged per pattern; max_scatter_px:
    dots moving more than this between samples are dropped; hold: still frames before
    sampling (SettleDetector)."""

    device: DotDevice
    schedule: Schedule
    samples: int = 3
    hold: int = 1
    max_scatter_px: float = 0.25
    max_settle_frames: int = 60
    settle: SettleDetector | None = None

    def calibrate_noise(self) -> None:
        """Hold a black screen and measure how much a still image changes (for settling)."""
        self.device.show(Dots.make(np.zeros((0, 2))))
        frames = [self.device.grab() for _ in range(8)]
        noise = signature_noise(frames[3:])
        self.settle = SettleDetector(noise=noise, hold=self.hold)
        self.settle.start(frames[-1])
        self.frames = getattr(self, "frames", 0) + len(frames)

    def _wait_still(self) -> None:
        """Before a view: wait until the user holds the target still."""
        assert self.settle is not None
        self.settle.start(expect_change=False)
        for _ in range(self.max_settle_frames):
            self.frames += 1
            if self.settle.feed(self.device.grab()):
                return
        raise UserError(f"the camera image kept changing for {self.max_settle_frames} "
                        "frames: hold the camera and monitor still")

    def _shoot(self, dots: Dots) -> tuple[np.ndarray, list[np.ndarray]]:
        """Show one pattern; the mean of the settled samples and the samples themselves."""
        assert self.settle is not None
        self.device.show(dots)
        self.settle.start()
        for _ in range(self.max_settle_frames):
            img = self.device.grab()
            self.frames += 1
            if self.settle.feed(img):
                break
        else:
            raise UserError(f"the camera image never settled after {self.max_settle_frames} "
                            "frames: hold the camera and monitor still, and turn off the "
                            "camera's auto exposure")
        shots = [_gray(img)]
        for _ in range(self.samples - 1):
            img = self.device.grab()
            self.frames += 1
            self.settle.feed(img)
            shots.append(_gray(img))
        return np.mean(shots, axis=0), shots

    def run(self, progress=None) -> DotView:
        """Show the whole schedule once and identify every dot the camera saw."""
        start_frames = getattr(self, "frames", 0)  # the first view pays for the noise too
        if self.settle is None:
            self.calibrate_noise()
        self._areas: list[float] = []
        self._moved = 0
        self._wait_still()
        sch = self.schedule
        if sch.kind == "raster":
            ids, uv, scatter, rejected = self._run_raster(progress)
        else:
            ids, uv, scatter, rejected = self._run_coded(progress)
        ids_a = np.concatenate(ids) if ids else np.zeros(0, np.int64)
        uv_a = np.concatenate(uv) if uv else np.zeros((0, 2))
        sc_a = np.concatenate(scatter) if scatter else np.zeros(0)
        # an id decoded twice is an error in one of them: drop both
        uniq, counts = np.unique(ids_a, return_counts=True)
        dup = np.isin(ids_a, uniq[counts > 1])
        rejected += int(dup.sum())
        radius = float(np.sqrt(np.median(self._areas) / np.pi)) if self._areas else float("nan")
        return DotView(ids_a[~dup], uv_a[~dup], sc_a[~dup], self.frames - start_frames,
                       rejected, radius, self._moved)

    def _run_raster(self, progress) -> tuple[list, list, list, int]:
        """One dot per frame: each frame's single dot is the one shown."""
        sch = self.schedule
        ids, uv, scatter, rejected = [], [], [], 0
        off, _ = self._shoot(Dots.make(np.zeros((0, 2))))
        for i, frame in enumerate(sch.frames):
            mean, shots = self._shoot(Dots.make(frame.xy, sch.radius_px))
            found, spread = self._find_dots(mean, off, shots)
            if len(found) == 1:
                ids.append(frame.ids)
                uv.append(found)
                scatter.append(spread)
            else:
                rejected += len(found)
            if progress is not None:
                progress(i + 1, len(sch.frames))
        return ids, uv, scatter, rejected

    def _run_coded(self, progress) -> tuple[list, list, list, int]:
        """Coded layers: decode the first, name the later ones from their neighbours (or
        decode each, when the schedule codes every layer)."""
        sch = self.schedule
        step_images: dict[int, np.ndarray | None] = {}
        on_shots: dict[int, list[np.ndarray]] = {}
        for i, frame in enumerate(sch.frames):
            mean, shots = self._shoot(Dots.make(frame.xy, sch.radius_px))
            step_images[i] = mean
            if frame.role == ROLE_ON:
                on_shots[i] = shots
            if progress is not None:
                progress(i + 1, len(sch.frames))
        return name_layers(sch, step_images,
                           lambda i, on, off: self._find_dots(on, off, on_shots[i]))

    def _find_dots(self, on: np.ndarray, off: np.ndarray, shots: list[np.ndarray]
                   ) -> tuple[np.ndarray, np.ndarray]:
        """Dots in (on - off): centroids and their scatter over the single samples; dots that
        moved, blurred into neighbours or lie cut by the screen edge are dropped."""
        diff = on - off
        cfg = DetectorConfig(threshold="auto", min_area=2.0, max_area=2000.0,
                             min_roundness=0.5)
        blobs = detect(diff, cfg)
        if len(blobs) == 0:
            return np.zeros((0, 2)), np.zeros(0)
        uv = blobs.uv
        threshold = blobs.threshold
        self._areas.extend(blobs.area.tolist())
        # a dot cut by the image border has a biased centroid; a blob far smaller than its
        # peers is a dot cut some other way (a bezel, an obstacle)
        h, w = diff.shape
        x0, y0, x1, y1 = blobs.bbox.T
        keep = (x0 > 0) & (y0 > 0) & (x1 < w - 1) & (y1 < h - 1)
        keep &= blobs.area >= 0.5 * np.median(blobs.area)
        per_shot = []
        for shot in shots:
            b = detect(shot - off, cfg.replace(threshold=threshold))
            j, d = _nearest(uv, b.uv)
            p = np.full_like(uv, np.nan)
            near = d < 1.0
            p[near] = b.uv[j[near]]
            per_shot.append(p)
        stack = np.stack(per_shot)
        # NaN (and so dropped below) where a sample missed the dot
        spread = np.sqrt(np.mean(np.sum((stack - uv) ** 2, axis=2), axis=0)) \
            if len(shots) > 1 else np.zeros(len(uv))
        seen_in_all = np.isfinite(stack).all(axis=(0, 2))
        moved = keep & (~seen_in_all | ~(spread <= self.max_scatter_px))
        self._moved += int(moved.sum())
        keep &= ~moved
        return uv[keep], spread[keep]
