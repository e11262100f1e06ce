"""caliscope's camera array (`camera_array.toml`, or an older `config.toml`) in and out.

What the keys mean, from caliscope's own code and proved on its data (docs/formats.md):

- `rotation`, `translation` are world-to-camera, OpenCV's convention, the same as ours:
  caliscope projects with `matrix @ [rotation | translation]`, and its triangulated points
  (calibration/extrinsic/stereotriangulated_points.csv) reproject onto its stored pixels
  through them to about a pixel, while the camera-to-world reading misses by 90-500 px
  (tests/test_rigformats.py). `rotation` is a 3x3 matrix (older files: a Rodrigues
  vector); `translation` is in metres (the board is measured in metres).
- `rotation_count` is how many quarter turns caliscope's UI turns the picture for display.
  Its intrinsics, `size` and every saved pixel stay in the camera's own, unturned frame
  (cameras with rotation_count 1 and -1 reproject onto pixels spanning 1280 x 720), so it
  changes nothing here: it is kept in the rig's meta and written back on export.
- `ignore = true` leaves a camera out of caliscope's calibration, so its pose is not part
  of the solution: such cameras are skipped, as are cameras without intrinsics or pose,
  and the rig's meta lists what was skipped and why.
"""

from __future__ import annotations

import re
from pathlib import Path

from calibkit.core.camera import Camera, Rig
from calibkit.core.errors import UserError
from calibkit.core.fileio import write_text_atomic
from calibkit.core.rigformats._common import (
    camera_matrix,
    distortion,
    floats,
    image_size,
    load_toml,
    make_camera,
    make_rig,
    number,
    numbers,
    pose_matrix,
    rotation_vector,
    table_sort_key,
    toml_tables,
)

FORMAT = "caliscope"
_LEGACY_TABLE = re.compile(r"^cam_(\d+)$")
_NAME = re.compile(r"^cam_(\d+)$")


def camera_tables(doc: dict) -> dict[str, dict] | None:
    """The per-camera tables of a caliscope file, by table name; None if it has none."""
    cams = doc.get("cameras")
    if isinstance(cams, dict) and cams and all(isinstance(v, dict) for v in cams.values()):
        return {str(k): v for k, v in cams.items()}
    legacy = {k: v for k, v in doc.items() if _LEGACY_TABLE.match(k) and isinstance(v, dict)}
    if legacy and any(("port" in v or "cam_id" in v) for v in legacy.values()):
        return legacy
    return None


def looks_like(doc: dict) -> bool:
    tables = camera_tables(doc)
    return tables is not None and all(
        ("cam_id" in t or "port" in t or "rotation_count" in t) and "name" not in t
        for t in tables.values())


def _present(table: dict, key: str) -> bool:
    value = table.get(key)
    return value is not None and value != "null" and value != ""


def read_caliscope(path: str | Path) -> Rig:
    """caliscope's calibrated cameras as a Rig; cameras are named `cam_<id>` (caliscope
    names its videos cam_<id>.mp4 and its CSVs' `cam_id` column holds <id>)."""
    path = Path(path)
    doc = load_toml(path)
    tables = camera_tables(doc)
    if tables is None:
        raise UserError(f"{path}: no [cameras.N] (or [cam_N]) tables: is this caliscope's "
                        "camera_array.toml?")
    cameras: list[Camera] = []
    skipped: list[str] = []
    extras: dict[str, dict] = {}
    for key in sorted(tables, key=table_sort_key):
        table = tables[key]
        where = f"{path}: camera [{key}]"
        cam_id = table.get("cam_id", table.get("port", key.removeprefix("cam_")))
        if isinstance(cam_id, str) and cam_id.strip().lstrip("-").isdigit():
            cam_id = int(cam_id)
        if isinstance(cam_id, bool) or not isinstance(cam_id, (int, float)) \
                or cam_id != cam_id or cam_id in (float("inf"), float("-inf")) \
                or cam_id != int(cam_id):
            raise UserError(f"{where}: 'cam_id' must be a whole number, got {cam_id!r}")
        cam_id = int(cam_id)
        name = f"cam_{cam_id}"
        if table.get("ignore") is True:
            skipped.append(f"{name}: ignore = true")
            continue
        missing = [k for k in ("size", "matrix", "distortions", "rotation", "translation")
                   if not _present(table, k)]
        if missing:
            skipped.append(f"{name}: no {', '.join(missing)} (not calibrated)")
            continue
        size = image_size(table["size"], f"{where} 'size'")
        K = camera_matrix(table["matrix"], f"{where} 'matrix'")
        dist = distortion(table["distortions"], f"{where} 'distortions'")
        rvec = rotation_vector(table["rotation"], f"{where} 'rotation'")
        t = numbers(table["translation"], (3,), f"{where} 'translation'")
        cameras.append(make_camera(name, size, K, dist, rvec, t, f"{where}:"))
        extra = {"cam_id": cam_id}
        for key_in, key_out in (("rotation_count", "rotation_count"), ("error", "error_px"),
                                ("grid_count", "grid_count")):
            if _present(table, key_in):
                extra[key_out] = number(table[key_in], f"{where} '{key_in}'")
        if "rotation_count" in extra:
            count = extra["rotation_count"]
            if count != int(count):
                raise UserError(f"{where} 'rotation_count' must be a whole number of quarter "
                                f"turns, got {count}")
            extra["rotation_count"] = int(count)
        if "grid_count" in extra:
            extra["grid_count"] = int(extra["grid_count"])
        extras[name] = extra
    meta = {"caliscope": extras}
    if skipped:
        meta["skipped_cameras"] = skipped
    return make_rig(cameras, path, FORMAT, meta)


def _ids(rig: Rig) -> list[int]:
    """caliscope's integer ids: the N of names cam_N when every name has one, else 0, 1..."""
    found = [_NAME.match(c.name) for c in rig]
    ids = [int(m.group(1)) for m in found if m]
    if len(ids) == len(rig) and len(set(ids)) == len(ids):
        return ids
    return list(range(len(rig)))


def caliscope_toml(rig: Rig) -> str:
    extras = rig.meta.get("caliscope", {}) if isinstance(rig.meta, dict) else {}
    tables = []
    for cam_id, cam in zip(_ids(rig), rig, strict=True):
        extra = extras.get(cam.name, {}) if isinstance(extras, dict) else {}
        table = {"cam_id": cam_id, "size": [cam.width, cam.height],
                 "rotation_count": int(extra.get("rotation_count", 0))}
        if "error_px" in extra:
            table["error"] = float(extra["error_px"])
        if "grid_count" in extra:
            table["grid_count"] = int(extra["grid_count"])
        table.update({"ignore": False, "matrix": floats(cam.K), "distortions": floats(cam.dist),
                      "translation": floats(cam.t), "rotation": floats(pose_matrix(cam))})
        tables.append((f"cameras.{cam_id}", table))
    return toml_tables(tables)


def write_caliscope(rig: Rig, path: str | Path) -> None:
    """The rig as caliscope's camera_array.toml ([cameras.N], rotation as a 3x3 matrix)."""
    write_text_atomic(Path(path), caliscope_toml(rig))


__all__ = ["read_caliscope", "write_caliscope", "looks_like"]
