"""The dot renderer (headless EGL), monitor listing, and the no-display errors."""

from __future__ import annotations

import numpy as np
import pytest

from calibkit.core.errors import UserError
from projector.display import OffscreenDisplay
from projector.dots import Dots
from projector.screens import Screen, list_screens, parse_pixel_pitch, parse_xrandr


def _centroids(img: np.ndarray, xy: np.ndarray, half: int) -> np.ndarray:
    out = []
    for x, y in xy:
        x0, y0 = int(round(x)) - half, int(round(y)) - half
        w = img[y0:y0 + 2 * half + 1, x0:x0 + 2 * half + 1].astype(np.float64)
        yy, xx = np.mgrid[y0:y0 + 2 * half + 1, x0:x0 + 2 * half + 1]
        out.append([(w * xx).sum() / w.sum(), (w * yy).sum() / w.sum(), w.sum()])
    return np.array(out)


@pytest.mark.parametrize("radius", [1.5, 3.0, 6.0])
def test_rendered_dot_centres_within_002_px(radius):
    rng = np.random.default_rng(1)
    gx, gy = np.meshgrid(np.arange(20, 300, 30.0), np.arange(20, 220, 30.0))
    xy = np.column_stack([gx.ravel(), gy.ravel()]) + rng.uniform(-0.5, 0.5, (gx.size, 2))
    with OffscreenDisplay((320, 240)) as display:
        img = display.render(Dots.make(xy, radius))
    c = _centroids(img, xy, int(radius) + 3)
    assert np.abs(c[:, :2] - xy).max() < 0.02
    # the coverage integrates to the disc's area
    np.testing.assert_allclose(c[:, 2], np.pi * radius ** 2, rtol=0.01)
    assert img.min() >= 0.0 and img.max() <= 1.0 + 1e-6


def test_render_u8_rows_top_down_and_empty_frame():
    with OffscreenDisplay((64, 48)) as display:
        img = display.render_u8(Dots.make([[10.0, 5.0]], 2.0))
        empty = display.render(Dots.make(np.zeros((0, 2))))
    assert img.dtype == np.uint8 and img.shape == (48, 64)
    assert img[5, 10] == 255 and img[40, 10] == 0  # row 0 is the top of the screen
    assert not empty.any()


def test_no_display_is_one_clear_error(monkeypatch):
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    with pytest.raises(UserError, match="no display found"):
        list_screens()


def test_displays_command_without_display(calibkit_cli, monkeypatch):
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    r = calibkit_cli("displays")
    assert r.code == 2
    assert "no display found" in r.err and len(r.err.strip().splitlines()) == 1
    assert "Traceback" not in r.err


def test_parse_xrandr_and_pixel_pitch():
    text = """Screen 0: minimum 8 x 8, current 3840 x 1080, maximum 32767 x 32767
DP-1 connected primary 1920x1080+0+0 (normal left inverted right x axis y) 527mm x 296mm
   1920x1080     60.00*+  50.00
HDMI-1 connected 1920x1080+1920+0 (normal left inverted right x axis y) 0mm x 0mm
   1920x1080     59.94*
VGA-1 disconnected (normal left inverted right x axis y)
"""
    screens = parse_xrandr(text)
    assert [s.name for s in screens] == ["DP-1", "HDMI-1"]
    a, b = screens
    assert (a.width_px, a.height_px, a.x_px, b.x_px) == (1920, 1080, 0, 1920)
    assert a.refresh_hz == 60.0 and b.refresh_hz == 59.94
    assert a.pixel_pitch_mm == pytest.approx(0.5 * (527 / 1920 + 296 / 1080))
    assert b.pixel_pitch_mm == 0.0  # unknown: the user must pass --pixel-pitch
    assert Screen(0, "x", 100, 100, 0, 0).pixel_pitch_mm == 0.0


def test_parse_pixel_pitch():
    assert parse_pixel_pitch("0.2745") == pytest.approx(0.2745)
    assert parse_pixel_pitch("527/1920") == pytest.approx(527 / 1920)
    assert parse_pixel_pitch(None) is None
    for bad in ("-0.2", "0", "abc", "1/0", "1/2/3", "nan"):
        with pytest.raises(UserError, match="--pixel-pitch takes"):
            parse_pixel_pitch(bad)
