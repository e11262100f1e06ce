"""anipose's `calibration.toml` (aniposelib's CameraGroup.dump) in and out; lengths in board units.

aniposelib writes tables `[cam_0]`, `[cam_1]`... in camera order with the camera's own
name in `name`; `size` is [width, height] (its Camera.set_size docstring) as integers;
`distortions` holds OpenCV's five coefficients; a fisheye camera is marked `fisheye =
true` (four fisheye coefficients, refused here) and a pinhole camera carries no `fisheye`
key at all; `[metadata]` has `adjusted` and `error`. anipose never states the unit of
`translation`: it is whatever the calibration board's size was given in (`mm` in anipose's
examples), so the reader and writer take it as an argument.
"""

from __future__ import annotations

from pathlib import Path

from calibkit.core.camera import Rig
from calibkit.core.fileio import write_text_atomic
from calibkit.core.rigformats._camtables import camera_table, read_tables, rms_px, write_text
from calibkit.core.rigformats._common import unit_m

FORMAT = "anipose"
DEFAULT_UNIT = "mm"


def read_anipose(path: str | Path, unit: str = DEFAULT_UNIT) -> Rig:
    """An anipose calibration as a Rig, its translations read as `unit` (mm, cm or m)."""
    rig = read_tables(Path(path), FORMAT, unit_m(unit))
    rig.meta["length_unit"] = unit
    return rig


def anipose_toml(rig: Rig, unit: str = DEFAULT_UNIT) -> str:
    scale = unit_m(unit)
    tables = [(f"cam_{i}", camera_table(cam, scale, size_as_floats=False, all_five=True))
              for i, cam in enumerate(rig)]
    return write_text(tables, {"adjusted": False, "error": rms_px(rig)})


def write_anipose(rig: Rig, path: str | Path, unit: str = DEFAULT_UNIT) -> None:
    write_text_atomic(Path(path), anipose_toml(rig, unit))
