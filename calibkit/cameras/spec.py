"""Camera specs: the text a user gives to name a camera, and opening the camera it names.

    0, 2, /dev/video2     an OpenCV device (V4L2 on Linux) by number
    shot.png              one image (one frame)
    frames/               a folder of images, in natural name order
    clip.mp4              a video file
    basler:SERIAL         a Basler camera through pypylon (basler: the first one found)
    genicam:SERIAL        a GenICam camera through harvesters and its maker's GenTL producer

One opener per kind in OPENERS: adding a kind is one entry there (and one in PLUGINS when it
needs a library that is not a dependency).
"""

from __future__ import annotations

import importlib.util
import logging
import re
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import cv2

from calibkit.cameras.base import FrameSource, Warn
from calibkit.cameras.basler import BaslerSource
from calibkit.cameras.genicam import GenICamSource
from calibkit.cameras.images import IMAGE_SUFFIXES, FolderSource, ImageSource
from calibkit.cameras.opencv import DeviceSource
from calibkit.cameras.video import VIDEO_SUFFIXES, VideoSource
from calibkit.core.errors import UserError

log = logging.getLogger("calibkit.cameras")

SPEC_HELP = ("give an image, a folder of images, a video file, a camera device number, "
             "basler:SERIAL or genicam:SERIAL")

# camera kinds that need a library we do not depend on: kind -> the module to import
PLUGINS = {"basler": "pypylon", "genicam": "harvesters"}


@dataclass(frozen=True)
class CameraSpec:
    """A parsed spec: kind ("device", "image", "folder", "video" or a plugin kind) and what
    names the camera within it (a device number, a path, a serial number; "" for a
    plugin's first camera)."""

    kind: str
    target: str


@dataclass(frozen=True)
class OpenOptions:
    """What a caller may ask of a camera as it opens; a kind that cannot apply an option
    ignores it (Capabilities says which it applies)."""

    fps: float | None = None
    size: tuple[int, int] | None = None
    exposure_us: float | None = None
    name: str | None = None
    warn: Warn = log.warning


def parse_spec(spec: str | Path) -> CameraSpec:
    """The kind of camera a spec names. Paths are looked at (a folder, an image or a video
    by suffix; an unknown suffix is an image if OpenCV reads it as one, else a video)."""
    text = str(spec).strip()
    if not text:
        raise UserError(f"an empty camera spec: {SPEC_HELP}")
    number = re.fullmatch(r"(?:/dev/video)?(\d+)", text)
    if number:
        return CameraSpec("device", number.group(1))
    kind, colon, rest = text.partition(":")
    if colon and kind.lower() in PLUGINS:
        return CameraSpec(kind.lower(), rest.strip())
    path = Path(text)
    if path.is_dir():
        return CameraSpec("folder", text)
    if not path.exists():
        if colon and re.fullmatch(r"[A-Za-z][\w-]*", kind):
            raise UserError(f"{text}: unknown camera kind {kind!r} ({SPEC_HELP})")
        raise UserError(f"{text} not found ({SPEC_HELP})")
    suffix = path.suffix.lower()
    if suffix in IMAGE_SUFFIXES:
        return CameraSpec("image", text)
    if suffix in VIDEO_SUFFIXES:
        return CameraSpec("video", text)
    if cv2.imread(text, cv2.IMREAD_UNCHANGED) is not None:
        return CameraSpec("image", text)
    return CameraSpec("video", text)


OPENERS: dict[str, Callable[[str, OpenOptions], FrameSource]] = {
    "device": lambda t, o: DeviceSource(int(t), o.size, o.fps, o.name, o.warn),
    "image": lambda t, o: ImageSource(t, o.name),
    "folder": lambda t, o: FolderSource(t, o.fps or 30.0, o.name),
    "video": lambda t, o: VideoSource(t, o.name),
    "basler": lambda t, o: BaslerSource(t, o.fps, o.exposure_us, o.name, o.warn),
    "genicam": lambda t, o: GenICamSource(t, o.fps, o.exposure_us, o.name, o.warn),
}


def open_camera(spec: str | Path, *, fps: float | None = None,
                size: tuple[int, int] | None = None, exposure_us: float | None = None,
                name: str | None = None, warn: Warn | None = None) -> FrameSource:
    """Open the camera a spec names (see the module docstring).

    fps: the frame rate to run a device at (read back, and `warn`ed about when the device
    reports another), or an image folder's timeline rate (default 30); files keep their own.
    size: (width, height) for an OpenCV device. exposure_us: for the industrial cameras
    (asking it of another kind is an error: none of them can apply it). name: the camera's
    name in its frames. warn: where the lines about a setting not taken go (default: the
    "calibkit.cameras" logger)."""
    parsed = parse_spec(spec)
    source = OPENERS[parsed.kind](parsed.target, OpenOptions(fps, size, exposure_us, name,
                                                             warn or log.warning))
    if exposure_us is not None and not source.capabilities.set_exposure:
        source.close()
        raise UserError(f"{spec}: this kind of camera ({parsed.kind}) cannot set the "
                        f"exposure time")
    return source


def missing_plugins(kinds) -> list[str]:
    """The camera kinds asked for whose library is not installed, as "kind (needs lib)"."""
    return [f"{k} (needs {PLUGINS[k]})" for k in kinds
            if k in PLUGINS and importlib.util.find_spec(PLUGINS[k]) is None]
