"""The `[cam_N]` camera-table TOML Pose2Sim and anipose share: read, written, differences passed in.

Both tools write one table per camera with `name`, `size` [width, height], `matrix` (K),
`distortions` (OpenCV's k1 k2 p1 p2 [k3]), `rotation` (a Rodrigues vector) and
`translation`, world-to-camera as OpenCV's solvePnP gives them, plus a `[metadata]` table.
What differs is left to pose2sim.py and anipose.py: the translation's unit, the table
names, whether `fisheye = false` is written, and the metadata.
"""

from __future__ import annotations

from pathlib import Path

from calibkit.core.camera import Camera, Rig
from calibkit.core.errors import UserError
from calibkit.core.rigformats._common import (
    camera_matrix,
    distortion,
    floats,
    image_size,
    load_toml,
    make_camera,
    make_rig,
    numbers,
    rotation_vector,
    table_sort_key,
    toml_tables,
)

REQUIRED = ("size", "matrix", "distortions", "rotation", "translation")


def camera_tables(doc: dict) -> dict[str, dict]:
    """Tables that hold a camera (a `matrix`), by table name; [metadata] and others left."""
    return {k: v for k, v in doc.items()
            if isinstance(v, dict) and k != "metadata" and "matrix" in v}


def looks_like(doc: dict) -> bool:
    tables = camera_tables(doc)
    return bool(tables) and all("distortions" in t and "rotation_count" not in t
                                and "cam_id" not in t for t in tables.values())


def read_tables(path: Path, fmt: str, unit_m: float) -> Rig:
    """Cameras from a Pose2Sim/anipose file; lengths in the file are `unit_m` metres each."""
    doc = load_toml(path)
    tables = camera_tables(doc)
    if not tables:
        raise UserError(f"{path}: no camera tables ([cam_1] with name, size, matrix, "
                        f"distortions, rotation, translation): is this a {fmt} calibration?")
    cameras: list[Camera] = []
    for key in sorted(tables, key=table_sort_key):
        table = tables[key]
        where = f"{path}: camera [{key}]"
        missing = [k for k in REQUIRED if k not in table]
        if missing:
            raise UserError(f"{where}: '{missing[0]}' is missing")
        if table.get("fisheye") is True:
            raise UserError(f"{where} is a fisheye camera (fisheye = true): calibkit models "
                            "only OpenCV's pinhole lens with k1 k2 p1 p2 k3; calibrate it "
                            "with the standard model")
        name = table.get("name", key)
        if not isinstance(name, str) or not name:
            raise UserError(f"{where}: 'name' must be a non-empty string, got {name!r}")
        size = image_size(table["size"], f"{where} 'size'")
        K = camera_matrix(table["matrix"], f"{where} 'matrix'")
        dist = distortion(table["distortions"], f"{where} 'distortions'")
        rvec = rotation_vector(table["rotation"], f"{where} 'rotation'")
        t = numbers(table["translation"], (3,), f"{where} 'translation'") * unit_m
        cameras.append(make_camera(name, size, K, dist, rvec, t, f"{where}:"))
    meta: dict = {}
    metadata = doc.get("metadata")
    if isinstance(metadata, dict):
        meta[fmt] = {k: v for k, v in metadata.items()
                     if isinstance(v, (bool, int, float, str))}
    return make_rig(cameras, path, fmt, meta)


def camera_table(cam: Camera, unit_m: float, size_as_floats: bool, all_five: bool) -> dict:
    """One camera's table. Without `all_five` the distortion keeps k3 only when it is not
    zero (Pose2Sim's own files carry four coefficients and OpenCV reads four or five
    alike); aniposelib unpacks exactly five, so anipose files get all five."""
    dist = cam.dist if all_five or cam.dist[4] != 0 else cam.dist[:4]
    size = [float(cam.width), float(cam.height)] if size_as_floats else [cam.width, cam.height]
    return {"name": cam.name, "size": size, "matrix": floats(cam.K),
            "distortions": floats(dist), "rotation": floats(cam.rvec),
            "translation": floats(cam.t / unit_m)}


def write_text(tables: list[tuple[str, dict]], metadata: dict) -> str:
    return toml_tables([*tables, ("metadata", metadata)])


def rms_px(rig: Rig) -> float:
    """The rig's recorded residual for the metadata's `error`, 0.0 when none is recorded."""
    for key in ("reprojection_rms_px", "held_out_rms_px"):
        value = rig.quality.get(key) if isinstance(rig.quality, dict) else None
        if isinstance(value, (int, float)) and value == value:
            return float(value)
    return 0.0
