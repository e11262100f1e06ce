"""Pose2Sim's calibration TOML (`Calib*.toml`) in and out: translation in metres, fisheye = false.

Pose2Sim names each table after its camera (`[cam_01]`, `[int_cam01_img]`) and repeats the
name in `name`; `size` is [width, height] written as floats; `distortions` holds k1 k2 p1
p2 (and k3 when not zero: OpenCV reads either); `[metadata]` has `adjusted` and `error`.
"""

from __future__ import annotations

from pathlib import Path

from calibkit.core.camera import Rig
from calibkit.core.fileio import write_text_atomic
from calibkit.core.rigformats._camtables import camera_table, read_tables, rms_px, write_text

FORMAT = "pose2sim"


def read_pose2sim(path: str | Path) -> Rig:
    """A Pose2Sim calibration as a Rig (its lengths are metres, like ours)."""
    return read_tables(Path(path), FORMAT, 1.0)


def pose2sim_toml(rig: Rig) -> str:
    tables = []
    for cam in rig:
        table = camera_table(cam, 1.0, size_as_floats=True, all_five=False)
        table["fisheye"] = False
        tables.append((cam.name, table))
    return write_text(tables, {"adjusted": False, "error": rms_px(rig)})


def write_pose2sim(rig: Rig, path: str | Path) -> None:
    write_text_atomic(Path(path), pose2sim_toml(rig))
