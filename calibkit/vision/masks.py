"""Per-camera masks of pixels to ignore: static reflections, lamps, other cameras' LEDs.

A mask is a bool image (True = ignore). On disk it is an 8-bit PNG, white (nonzero) where
pixels are ignored, so a user can paint one by hand as well. `build_mask` makes one the way
commercial systems do: record a few frames with no markers in view; whatever is bright
there is not a marker, so it is masked, dilated a little so that the flicker at its edge
stays masked too.
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

import cv2
import numpy as np

from calibkit.core.errors import UserError
from calibkit.core.fileio import write_bytes_atomic
from calibkit.vision.detect import DetectorConfig, auto_threshold


def load_mask(path: str | Path, size: tuple[int, int] | None = None) -> np.ndarray:
    """Read a mask PNG -> bool (h, w), True where pixels are ignored; `size` = (w, h) checks it."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"mask file {path} not found; make one with `calibkit mask SOURCE "
                        f"--out {path.name}`")
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise UserError(f"{path} is not an image OpenCV can read; a mask is an 8-bit PNG")
    if img.ndim == 3:
        img = img.max(axis=2)
    mask = img > 0
    if size is not None and (mask.shape[1], mask.shape[0]) != tuple(size):
        raise UserError(f"mask {path} is {mask.shape[1]}x{mask.shape[0]} but the camera is "
                        f"{size[0]}x{size[1]}; build the mask from this camera's frames")
    return mask


def save_mask(path: str | Path, mask: np.ndarray) -> None:
    """Write a mask as an 8-bit PNG (255 = ignored), atomically."""
    mask = np.asarray(mask, dtype=bool)
    ok, data = cv2.imencode(".png", mask.astype(np.uint8) * 255)
    if not ok:  # pragma: no cover - OpenCV always encodes a 2D uint8 array
        raise RuntimeError("PNG encoding failed")
    write_bytes_atomic(path, data.tobytes())


def build_mask(frames: Iterable[np.ndarray], threshold: float | str = "auto",
               dilate_px: int = 4, config: DetectorConfig | None = None) -> np.ndarray:
    """Mask of the pixels that are bright in any of `frames` (taken with no markers in view).

    threshold: a pixel value or "auto" (each frame's background plus the detector's margin,
    the same level detection uses, so what the mask hides is exactly what would have been
    detected). dilate_px: grow the masked areas by this many pixels (a disc).
    """
    config = config or DetectorConfig()
    if dilate_px < 0:
        raise UserError(f"--dilate must be >= 0 pixels, got {dilate_px}")
    bright = None
    for image in frames:
        gray = np.asarray(image)
        if gray.ndim == 3:
            gray = cv2.cvtColor(gray, cv2.COLOR_BGRA2GRAY if gray.shape[2] == 4
                                else cv2.COLOR_BGR2GRAY)
        level = auto_threshold(gray, config) if threshold == "auto" else float(threshold)
        above = gray > level
        if bright is None:
            bright = above
        elif bright.shape != above.shape:
            raise UserError(f"frames differ in size ({bright.shape[1]}x{bright.shape[0]} vs "
                            f"{above.shape[1]}x{above.shape[0]}); build a mask per camera")
        else:
            bright |= above
    if bright is None:
        raise UserError("no frames to build the mask from")
    if dilate_px > 0 and bright.any():
        d = 2 * dilate_px + 1
        kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (d, d))
        bright = cv2.dilate(bright.view(np.uint8), kernel) > 0
    return bright
