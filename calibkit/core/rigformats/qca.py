"""Qualisys QTM's calibration export (`.qca`, `.qca.txt`, XML) read into a Rig: import only.

What each attribute means (QTM's export, Pose2Sim's converter read for the facts, and
checked on the real file in fixtures/pose2sim_chessboard_4cam; docs/formats.md):

- `<transform x y z r11..r33>`: the camera's position in the world, in millimetres, and
  its orientation with r_ij stored column by column, so the matrix M = [[r11 r12 r13],
  ...] is world-to-camera for QTM's camera axes, which look down -z with y up. OpenCV's
  camera looks down +z with y down: R = diag(1, -1, -1) M, t = -R x. Every camera of the
  sample then looks at the capture volume's centre (cos > 0.94), and the rotation vectors
  equal Pose2Sim's own conversion of the same file.
- `<intrinsic>` focal lengths, principal point (and skew) are in sensor sub-pixels, 64
  to a pixel in the files QTM writes (`sensorMaxU` 69568 = 64 x 1087): the divisor, 64 or
  1, is the one that puts the principal point nearest the sensor's centre, so a file
  already in pixels reads too. The principal point counts from the sensor's corner; the
  video image is the `fov_video` window (right - left + 1 by bottom - top + 1 pixels), so
  its left and top are subtracted.
- `radialDistortion1..3`, `tangentalDistortion1..2` are OpenCV's k1 k2 k3 p1 p2 as they
  are (dimensionless, on normalised coordinates). Pose2Sim divides them by 64 too; on the
  sample that gives k1 = -0.0007, while OpenCV calibrating the same camera's chessboard
  images with QTM's K held gives k1 = -0.046 against the file's -0.0462.
- `video_resolution="540p"` (Miqus video cameras filming below full resolution) scales
  the image and intrinsics by 540 over the sensor's nominal height (the largest of
  2160/1440/1080/720/540/480 lines that fits the sensor's short side: 1080 for a
  1920 x 1088 sensor, 1440 for 1920 x 1440).
- Inactive cameras (`active="0"`) and cameras QTM marks `calibrated="false"` are skipped
  and listed in the rig's meta; `avg-residual` (mm), `model` and `viewrotation` (display
  only, like caliscope's rotation_count) are kept there too.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from calibkit.core.camera import Camera, Rig, rvec_from_rotation
from calibkit.core.errors import UserError
from calibkit.core.rigformats._common import (
    make_camera,
    make_rig,
    numbers,
    read_bytes,
    rotation_matrix,
)

FORMAT = "qca"
SUBPIXELS = (64.0, 1.0)
NOMINAL_LINES = (2160, 1440, 1080, 720, 540, 480)
QTM_TO_OPENCV = np.diag([1.0, -1.0, -1.0])


def _value(element: ET.Element, key: str, where: str, default: float | None = None) -> float:
    text = element.get(key)
    if text is None:
        if default is not None:
            return default
        raise UserError(f"{where}: <{element.tag}> has no '{key}' attribute")
    try:
        value = float(text)
    except ValueError:
        raise UserError(f"{where}: <{element.tag}> '{key}' must be a number, got {text!r}") \
            from None
    return float(numbers([value], (1,), f"{where}: <{element.tag}> '{key}'")[0])


def _window(camera: ET.Element, tag: str, where: str) -> tuple[float, float, float, float] | None:
    """(left, top, right, bottom) of a fov_* element, inclusive pixel bounds; None if absent."""
    element = camera.find(tag)
    if element is None:
        return None
    box = tuple(_value(element, k, where) for k in ("left", "top", "right", "bottom"))
    if box[2] < box[0] or box[3] < box[1]:
        raise UserError(f"{where}: <{tag}> right/bottom lie before left/top: {box}")
    return box  # type: ignore[return-value]


def looks_like(data: bytes) -> bool:
    head = data[:4096].lstrip()
    return head.startswith(b"<") and b"<calibration" in head and b"<cameras" in data


def _subpixel(intrinsic: ET.Element, sensor: tuple, where: str) -> float:
    """64 or 1: the divisor that puts the principal point nearest the sensor's centre."""
    cu, cv = _value(intrinsic, "centerPointU", where), _value(intrinsic, "centerPointV", where)
    centre = np.array([(sensor[0] + sensor[2]) / 2, (sensor[1] + sensor[3]) / 2])
    offsets = [np.hypot(*(np.array([cu, cv]) / s - centre)) for s in SUBPIXELS]
    return SUBPIXELS[int(np.argmin(offsets))]


def _video_scale(camera: ET.Element, sensor: tuple, where: str) -> float:
    text = camera.get("video_resolution")
    if text in (None, "", "N/A"):
        return 1.0
    try:
        lines = int(text.lower().removesuffix("p"))
    except ValueError:
        raise UserError(f"{where}: video_resolution must look like '1080p', got {text!r}") \
            from None
    short = min(sensor[2] - sensor[0], sensor[3] - sensor[1]) + 1
    nominal = next((n for n in NOMINAL_LINES if n <= short), short)
    if lines <= 0 or lines > nominal:
        raise UserError(f"{where}: video_resolution {text!r} is larger than the sensor's "
                        f"{nominal} lines")
    return lines / nominal


def _camera(camera: ET.Element, name: str, where: str) -> Camera:
    transform, intrinsic = camera.find("transform"), camera.find("intrinsic")
    for element, tag in ((transform, "transform"), (intrinsic, "intrinsic")):
        if element is None:
            raise UserError(f"{where}: no <{tag}> element")
    M = rotation_matrix([[_value(transform, f"r{i}{j}", where) for j in (1, 2, 3)]
                         for i in (1, 2, 3)], f"{where}: <transform> r11..r33")
    position_m = np.array([_value(transform, k, where) for k in ("x", "y", "z")]) / 1000.0
    R = QTM_TO_OPENCV @ M
    video = _window(camera, "fov_video", where) or _window(camera, "fov_marker", where)
    if video is None:
        raise UserError(f"{where}: no <fov_video> (or <fov_marker>) element: the image size "
                        "is unknown")
    sensor = (_window(camera, "fov_video_max", where) or _window(camera, "fov_marker_max", where)
              or video)
    sub = _subpixel(intrinsic, sensor, where)
    scale = _video_scale(camera, sensor, where)
    fu = _value(intrinsic, "focalLengthU", where) / sub
    fv = _value(intrinsic, "focalLengthV", where) / sub
    cu = _value(intrinsic, "centerPointU", where) / sub - video[0]
    cv = _value(intrinsic, "centerPointV", where) / sub - video[1]
    skew = _value(intrinsic, "skew", where, 0.0) / sub
    K = np.array([[fu, skew, cu], [0.0, fv, cv], [0.0, 0.0, 1.0]])
    K[:2] *= scale
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        raise UserError(f"{where}: <intrinsic> focal lengths must be positive")
    size = (round((video[2] - video[0] + 1) * scale), round((video[3] - video[1] + 1) * scale))
    dist = np.array([_value(intrinsic, k, where, 0.0) for k in (
        "radialDistortion1", "radialDistortion2", "tangentalDistortion1",
        "tangentalDistortion2", "radialDistortion3")])
    return make_camera(name, size, K, dist, rvec_from_rotation(R), -R @ position_m,
                       f"{where}:")


def read_qca(path: str | Path) -> Rig:
    """A QTM calibration as a Rig, cameras named by their serial, in the file's order."""
    path = Path(path)
    data = read_bytes(path)
    try:
        root = ET.fromstring(data)
    except ET.ParseError as exc:
        raise UserError(f"{path}: not valid XML ({exc})") from None
    cameras_xml = root.findall("cameras/camera") if root.tag == "calibration" else []
    if not cameras_xml:
        raise UserError(f"{path}: no <calibration><cameras><camera> elements: is this a "
                        "QTM .qca calibration?")
    cameras, skipped, extras = [], [], {}
    for i, element in enumerate(cameras_xml):
        name = element.get("serial") or f"cam_{i + 1}"
        where = f"{path}: camera '{name}'"
        if element.get("active", "1").strip() == "0":
            skipped.append(f"{name}: active = 0")
            continue
        if element.get("calibrated", "true").strip().lower() == "false":
            skipped.append(f"{name}: calibrated = false")
            continue
        cameras.append(_camera(element, name, where))
        extra = {k.replace("-", "_"): element.get(k)
                 for k in ("model", "viewrotation", "video_resolution") if element.get(k)}
        if element.get("avg-residual") is not None:
            extra["avg_residual_mm"] = _value(element, "avg-residual", where)
        extras[name] = extra
    meta = {"qca": extras}
    if skipped:
        meta["skipped_cameras"] = skipped
    return make_rig(cameras, path, FORMAT, meta)
