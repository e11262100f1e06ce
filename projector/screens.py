"""Finding the monitors and projectors attached to this machine, and their pixel pitch.

The pixel pitch turns screen pixels into millimetres, so it sets the scale of every
calibration point: it comes from the monitor's reported physical size (EDID), and the user
can override it when the EDID is wrong (projectors report nonsense; some monitors report 0).
Monitors are read through glfw when it is installed, else from `xrandr --query`.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
from dataclasses import dataclass

from calibkit.core.errors import UserError


@dataclass(frozen=True)
class Screen:
    """One monitor: its position on the desktop and size in pixels, physical size in mm
    (0 when unknown), refresh rate in Hz (0 when unknown)."""

    index: int
    name: str
    width_px: int
    height_px: int
    width_mm: float
    height_mm: float
    x_px: int = 0
    y_px: int = 0
    refresh_hz: float = 0.0

    @property
    def pixel_pitch_mm(self) -> float:
        """Millimetres per pixel (mean of both axes); 0 when the size is unknown."""
        if self.width_mm <= 0 or self.height_mm <= 0:
            return 0.0
        return 0.5 * (self.width_mm / self.width_px + self.height_mm / self.height_px)


def parse_pixel_pitch(text: str | None) -> float | None:
    """`--pixel-pitch`: mm per pixel, as a number (0.2745) or a ratio (527/1920: the
    picture's width in mm over its width in pixels)."""
    if text is None:
        return None
    try:
        parts = [float(v) for v in str(text).split("/")]
        value = parts[0] / parts[1] if len(parts) == 2 else parts[0]
        if len(parts) > 2 or not value > 0 or value != value or value == float("inf"):
            raise ValueError
    except (ValueError, ZeroDivisionError):
        raise UserError(f"--pixel-pitch takes mm per pixel, like 0.2745 or 527/1920 (width "
                        f"in mm / width in pixels); got {text!r}") from None
    return value


def display_available() -> bool:
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def require_display() -> None:
    if not display_available():
        raise UserError("no display found (neither DISPLAY nor WAYLAND_DISPLAY is set): run "
                        "on a machine with a monitor attached, or use --sim")


_XRANDR_LINE = re.compile(
    r"^(?P<name>\S+) connected (?:primary )?(?P<w>\d+)x(?P<h>\d+)\+(?P<x>\d+)\+(?P<y>\d+)"
    r".*?(?:(?P<wmm>\d+)mm x (?P<hmm>\d+)mm)?\s*$")


def parse_xrandr(text: str) -> list[Screen]:
    """Connected, active outputs from `xrandr --query` output."""
    screens = []
    lines = text.splitlines()
    for i, line in enumerate(lines):
        m = _XRANDR_LINE.match(line)
        if not m:
            continue
        hz = 0.0
        for mode in lines[i + 1:]:
            if not mode.startswith(" "):
                break
            if "*" in mode:
                rate = re.search(r"([\d.]+)\*", mode)
                hz = float(rate.group(1)) if rate else 0.0
                break
        screens.append(Screen(len(screens), m["name"], int(m["w"]), int(m["h"]),
                              float(m["wmm"] or 0), float(m["hmm"] or 0), int(m["x"]),
                              int(m["y"]), hz))
    return screens


def _glfw_screens() -> list[Screen] | None:
    try:
        # deferred on purpose: loads glfw only where used
        import glfw
    except ModuleNotFoundError:
        return None
    if not glfw.init():
        return None
    try:
        out = []
        for i, mon in enumerate(glfw.get_monitors()):
            mode = glfw.get_video_mode(mon)
            wmm, hmm = glfw.get_monitor_physical_size(mon)
            x, y = glfw.get_monitor_pos(mon)
            name = glfw.get_monitor_name(mon)
            out.append(Screen(i, name.decode() if isinstance(name, bytes) else str(name),
                              mode.size.width, mode.size.height, float(wmm), float(hmm),
                              x, y, float(mode.refresh_rate)))
        return out
    finally:
        glfw.terminate()


def list_screens() -> list[Screen]:
    """Every monitor attached; a UserError when there is no display at all."""
    require_display()
    screens = _glfw_screens()
    if screens is None and shutil.which("xrandr"):
        try:
            text = subprocess.run(["xrandr", "--query"], capture_output=True, text=True,
                                  timeout=10, check=False).stdout
        except (OSError, subprocess.TimeoutExpired):
            text = ""
        screens = parse_xrandr(text)
    if screens is None:
        raise UserError("cannot list monitors: install the 'glfw' package (pip install glfw) "
                        "or the xrandr tool")
    if not screens:
        raise UserError("no monitor found on this display")
    return screens


def pick_screen(index: int, pixel_pitch_mm: float | None = None) -> tuple[Screen, float]:
    """The screen to draw on and its pixel pitch (the override wins over the EDID)."""
    screens = list_screens()
    if not 0 <= index < len(screens):
        raise UserError(f"no monitor {index}: found {len(screens)} (see `calibkit displays`)")
    screen = screens[index]
    pitch = pixel_pitch_mm if pixel_pitch_mm is not None else screen.pixel_pitch_mm
    if not pitch or pitch <= 0:
        raise UserError(f"monitor {index} ({screen.name}) does not report its physical size: "
                        "measure the picture's width in mm and pass --pixel-pitch "
                        f"WIDTH_MM/{screen.width_px}")
    return screen, pitch
