"""Capturing a dot schedule with one camera: show, wait to settle, average, detect, decode.

For each frame of a schedule (projector.patterns) the display is asked to show it; camera
frames are fed to a SettleDetector until the image has settled; then `samples` frames are
averaged. Dots are detected on (all-on - all-off) of each layer, which removes the screen's
glow and any room light; each dot's position is also measured in every single all-on
sample, and dots whose scatter is large (the monitor or camera moved, motion blur) are
dropped. The decoder then names each dot. The result is a table of (point id, image
position, scatter) per view.

`DotDevice` is all this needs from hardware: `show(dots)` and `grab() -> image`. A monitor
and a webcam, a projector and one camera of a rig, or the simulator all fit. The finding
and naming of dots in settled images (`find_dots`, `identify_dots`, one `DotFilter`) is
shared with the projector capture of a whole rig (calibkit.calibrate.extrinsic_capture),
which settles several cameras at once but sees its dots the same way.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from calibkit.calibrate.settle import SettleDetector, signature_noise
from calibkit.core.errors import UserError
from calibkit.vision.detect import DetectorConfig, detect
from calibkit.vision.gray import to_gray
from projector.dots import Dots
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


def _nearest(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For each row of a: index of the nearest row of b and its distance (b may be empty)."""
    if len(b) == 0:
        return np.zeros(len(a), np.int64), np.full(len(a), np.inf)
    # deferred on purpose: loads SciPy's sparse graphs, SciPy's spatial only where used
    from scipy.spatial import cKDTree

    d, i = cKDTree(b).query(a)
    return np.asarray(i, np.int64), np.asarray(d, np.float64)


@dataclass(frozen=True)
class DotFilter:
    """Which detected dots to keep.

    min_roundness: blobs less round than this are merged or smeared dots; min_area_ratio:
    a blob smaller than this share of the median dot area is cut (a bezel, an obstacle,
    an edge of the projection) and its centroid biased; max_scatter_px: a dot whose
    centroid moves more than this between the single samples moved (the target, the
    camera, a blurred frame); drop_border: a blob touching the image border is cut by it.
    The defaults were chosen on the simulator against the true dot positions
    (benchmarks/bench_dotfilter.py, docs/intrinsic.md): the border check removed every
    dot off by more than 1 px in the projector captures; roundness 0.4 keeps the
    projector's obliquely seen dots (a third more than 0.5) with no gross error, and costs
    the monitor nothing; area and scatter made no difference worth a dot."""

    min_roundness: float = 0.4
    min_area_ratio: float = 0.4
    max_scatter_px: float = 0.25
    drop_border: bool = True


DOT_FILTER = DotFilter()


@dataclass(frozen=True, eq=False)
class FoundDots:
    """Dots kept in one layer: centroids (N, 2) px, their scatter over the samples (N,) px;
    the areas (px) of every dot detected, and how many were dropped for moving."""

    uv: np.ndarray
    scatter_px: np.ndarray
    areas: np.ndarray = field(default_factory=lambda: np.zeros(0))
    moved: int = 0


def find_dots(on: np.ndarray, off: np.ndarray, shots: list[np.ndarray],
              dot_filter: DotFilter = DOT_FILTER) -> FoundDots:
    """Dots in (on - off): centroids and their scatter over the single samples `shots`;
    dots that moved, blurred into neighbours or are cut are dropped (`dot_filter`)."""
    diff = on - off
    cfg = DetectorConfig(threshold="auto", min_area=2.0, max_area=2000.0,
                         min_roundness=dot_filter.min_roundness)
    blobs = detect(diff, cfg)
    if len(blobs) == 0:
        return FoundDots(np.zeros((0, 2)), np.zeros(0))
    uv = blobs.uv
    keep = blobs.area >= dot_filter.min_area_ratio * np.median(blobs.area)
    if dot_filter.drop_border:
        h, w = diff.shape
        x0, y0, x1, y1 = blobs.bbox.T
        keep &= (x0 > 0) & (y0 > 0) & (x1 < w - 1) & (y1 < h - 1)
    per_shot = []
    for shot in shots:
        b = detect(shot - off, cfg.replace(threshold=blobs.threshold))
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
    moved = keep & (~seen_in_all | ~(spread <= dot_filter.max_scatter_px))
    keep &= ~moved
    return FoundDots(uv[keep], spread[keep], blobs.area, int(moved.sum()))


@dataclass(frozen=True, eq=False)
class NamedDots:
    """Every dot one camera saw in a schedule, named: point ids (N,), image positions
    (N, 2) px, scatter (N,) px; rejected: detections not named (or named twice); the
    detected dots' areas and the dots dropped for moving, over all layers."""

    ids: np.ndarray
    uv: np.ndarray
    scatter_px: np.ndarray
    rejected: int
    areas: np.ndarray
    moved: int


def identify_dots(schedule: Schedule, step_images: dict[int, np.ndarray | None],
                  on_shots: dict[int, list[np.ndarray]],
                  dot_filter: DotFilter = DOT_FILTER) -> NamedDots:
    """Name the dots of a coded schedule's settled images (mean per pattern; None where
    the camera gave none) from the single samples of each all-on pattern: the first layer
    by its code, later layers by their named neighbours (projector.patterns.name_layers).
    A name given twice is wrong once: both go."""
    areas: list[np.ndarray] = []
    moved = 0

    def find(i: int, on: np.ndarray, off: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        nonlocal moved
        found = find_dots(on, off, on_shots[i], dot_filter)
        areas.append(found.areas)
        moved += found.moved
        return found.uv, found.scatter_px

    ids, uv, scatter, rejected = name_layers(schedule, step_images, find)
    return _named(ids, uv, scatter, rejected, areas, moved)


def _named(ids: list, uv: list, scatter: list, rejected: int, areas: list[np.ndarray],
           moved: int) -> NamedDots:
    ids_a = np.concatenate(ids) if ids else np.zeros(0, np.int64)
    uv_a = np.concatenate(uv) if uv else np.zeros((0, 2))
    sc_a = np.concatenate(scatter) if scatter else np.zeros(0)
    uniq, counts = np.unique(ids_a, return_counts=True)
    dup = np.isin(ids_a, uniq[counts > 1])
    return NamedDots(ids_a[~dup], uv_a[~dup], sc_a[~dup], rejected + int(dup.sum()),
                     np.concatenate(areas) if areas else np.zeros(0), moved)


@dataclass
class DotCapture:
    """Runs a schedule on a device. samples: frames averaged per pattern; dot_filter: which
    dots to keep (DotFilter); hold: still frames before sampling (SettleDetector)."""

    device: DotDevice
    schedule: Schedule
    samples: int = 3
    hold: int = 1
    dot_filter: DotFilter = DOT_FILTER
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
        shots = [to_gray(img, np.float32)]
        for _ in range(self.samples - 1):
            img = self.device.grab()
            self.frames += 1
            self.settle.feed(img)
            shots.append(to_gray(img, np.float32))
        return np.mean(shots, axis=0), shots

    def run(self, progress=None) -> DotView:
        """Show the whole schedule once and identify every dot the camera saw."""
        start_frames = getattr(self, "frames", 0)  # the first view pays for the noise too
        if self.settle is None:
            self.calibrate_noise()
        self._wait_still()
        if self.schedule.kind == "raster":
            named = self._run_raster(progress)
        else:
            named = self._run_coded(progress)
        radius = (float(np.sqrt(np.median(named.areas) / np.pi)) if len(named.areas)
                  else float("nan"))
        return DotView(named.ids, named.uv, named.scatter_px, self.frames - start_frames,
                       named.rejected, radius, named.moved)

    def _run_raster(self, progress) -> NamedDots:
        """One dot per frame: each frame's single dot is the one shown."""
        sch = self.schedule
        ids, uv, scatter, areas, rejected, moved = [], [], [], [], 0, 0
        off, _ = self._shoot(Dots.make(np.zeros((0, 2))))
        for i, frame in enumerate(sch.frames):
            mean, shots = self._shoot(Dots.make(frame.xy, sch.radius_px))
            found = find_dots(mean, off, shots, self.dot_filter)
            areas.append(found.areas)
            moved += found.moved
            if len(found.uv) == 1:
                ids.append(frame.ids)
                uv.append(found.uv)
                scatter.append(found.scatter_px)
            else:
                rejected += len(found.uv)
            if progress is not None:
                progress(i + 1, len(sch.frames))
        return _named(ids, uv, scatter, rejected, areas, moved)

    def _run_coded(self, progress) -> NamedDots:
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
        return identify_dots(sch, step_images, on_shots, self.dot_filter)
