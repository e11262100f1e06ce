"""Image files as cameras: one image (one frame) or a folder of images at a chosen rate."""

from __future__ import annotations

import re
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np

from calibkit.cameras.base import Capabilities, Frame, FrameSource
from calibkit.core.errors import UserError

IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm", ".ppm", ".webp"}


def read_image(path: Path) -> np.ndarray:
    """An image as the file holds it (grayscale or BGR, 8 or 16 bit; alpha dropped)."""
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise UserError(f"{path} is not an image OpenCV can read")
    if image.ndim == 3 and image.shape[2] == 4:
        image = cv2.cvtColor(image, cv2.COLOR_BGRA2BGR)
    return image


def natural_key(path: Path) -> list:
    """A sort key that puts frame2 before frame10."""
    return [int(p) if p.isdigit() else p for p in re.split(r"(\d+)", path.name)]


def image_files(folder: Path) -> list[Path]:
    """The images of a folder (by suffix) in natural name order."""
    return sorted((p for p in folder.iterdir()
                   if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file()), key=natural_key)


class ImageSource(FrameSource):
    """A single image file: one frame, at time 0."""

    def __init__(self, path: str | Path, camera: str | None = None) -> None:
        self.path = Path(path)
        if not self.path.is_file():
            raise UserError(f"image {self.path} not found")
        self.camera = camera or self.path.stem

    def __iter__(self) -> Iterator[Frame]:
        yield Frame(self.camera, 0, 0, read_image(self.path))


class FolderSource(FrameSource):
    """The images of a folder in natural name order (frame2 before frame10), stamped at
    `fps` from time 0 (the folder has no clock of its own: all folders share this one)."""

    capabilities = Capabilities(set_fps=True)

    def __init__(self, path: str | Path, fps: float = 30.0, camera: str | None = None) -> None:
        self.path = Path(path)
        if not self.path.is_dir():
            raise UserError(f"folder {self.path} not found")
        self.files = image_files(self.path)
        if not self.files:
            raise UserError(f"folder {self.path} holds no images "
                            f"({', '.join(sorted(IMAGE_SUFFIXES))})")
        if not fps > 0:
            raise UserError(f"fps must be positive, got {fps}")
        self.fps = fps
        self.camera = camera or self.path.name

    def __iter__(self) -> Iterator[Frame]:
        for i, f in enumerate(self.files):
            yield Frame(self.camera, i, round(i * 1e9 / self.fps), read_image(f))
