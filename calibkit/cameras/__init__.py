"""Cameras: one interface for every kind, used by every calibration command and the daemon.

`open_camera(spec)` opens what a user named (calibkit.cameras.spec: a device number, an
image, a folder, a video, `basler:SERIAL`, `genicam:SERIAL`); the result is a FrameSource
(calibkit.cameras.base): iterate it for Frames (capture time, index, image, and the
device's own timestamp and counter where it gives them), ask its `capabilities`, close it.
One module per kind: opencv, video, images, basler, genicam. The simulated camera is a
FrameSource too, in calibkit.synthetic.frames (it carries the truth, so it lives apart).

Part of calibkit's core layer: it imports nothing from the commands, the simulator, the
daemon or the display.
"""

from calibkit.cameras.base import Capabilities, Frame, FrameSource, Warn
from calibkit.cameras.spec import (
    PLUGINS,
    SPEC_HELP,
    CameraSpec,
    missing_plugins,
    open_camera,
    parse_spec,
)

__all__ = ["PLUGINS", "SPEC_HELP", "CameraSpec", "Capabilities", "Frame", "FrameSource",
           "Warn", "missing_plugins", "open_camera", "parse_spec"]
