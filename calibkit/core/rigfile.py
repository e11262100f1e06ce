"""Reading and writing rig files: our `rig.toml`, and OpenCV FileStorage YAML for other tools.

The TOML format is documented in docs/formats.md. Loading validates every field and names
the file, the camera and the field in its one-line error, because a hand-edited rig file
is the most common way a user breaks a run.

Reading gives checked plain values (RigFields), which `Rig.load` turns into cameras, so
this module needs nothing from calibkit.core.camera at run time and the two do not import
each other; writing reads a rig's attributes.
"""

from __future__ import annotations

import datetime as _dt
import math
import os
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from calibkit.core.errors import UserError
from calibkit.core.fileio import write_text_atomic

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib  # type: ignore[no-redef]

if TYPE_CHECKING:
    from calibkit.core.camera import Camera, Rig

FORMAT = "calibkit-rig"
VERSION = 1


class RigFields(NamedTuple):
    """A rig file's checked contents: per camera the keyword arguments of Camera (name,
    size, fx, fy, cx, cy, skew, dist, rvec, t), and the free-form tables."""

    cameras: list[dict]
    quality: dict
    meta: dict


def _matrix(value, shape: tuple[int, ...], where: str) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise UserError(f"{where} must be numbers shaped {shape}, got {value!r}") from None
    if arr.size != math.prod(shape):
        raise UserError(f"{where} must be shaped {shape}, got {list(arr.shape)}")
    arr = arr.reshape(shape)
    if not np.all(np.isfinite(arr)):
        raise UserError(f"{where} holds a value that is not a finite number")
    return arr


def camera_args(fields: dict, where: str) -> dict:
    """Check a TOML/YAML camera table and give Camera's keyword arguments from it; `where`
    prefixes every error."""
    if not isinstance(fields, dict):
        raise UserError(f"{where}: a camera must be a table")
    name = fields.get("name")
    if not isinstance(name, str) or not name:
        raise UserError(f"{where}: field 'name' is missing or not a string")
    where = f"{where} camera '{name}':"
    for key in ("size", "K", "dist", "R", "t"):
        if key not in fields:
            raise UserError(f"{where} field '{key}' is missing")
    size = _matrix(fields["size"], (2,), f"{where} field 'size'")
    if np.any(size < 1) or np.any(size != np.round(size)):
        raise UserError(f"{where} field 'size' must be two positive integers [width, height]")
    K = _matrix(fields["K"], (3, 3), f"{where} field 'K'")
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        raise UserError(f"{where} field 'K' must have positive focal lengths")
    if not np.allclose(K[2], [0, 0, 1]) or abs(K[1, 0]) > 0:
        raise UserError(f"{where} field 'K' must be [[fx, skew, cx], [0, fy, cy], [0, 0, 1]]")
    dist = np.asarray(fields["dist"], dtype=object).ravel()
    if dist.size not in (4, 5):
        raise UserError(f"{where} field 'dist' must be [k1, k2, p1, p2, k3]")
    dist = _matrix(list(dist), (dist.size,), f"{where} field 'dist'")
    R = np.asarray(fields["R"], dtype=object)
    if R.size == 9:
        Rm = _matrix(fields["R"], (3, 3), f"{where} field 'R'")
        if not np.allclose(Rm @ Rm.T, np.eye(3), atol=1e-6) or np.linalg.det(Rm) < 0:
            raise UserError(f"{where} field 'R' is not a rotation matrix")
        # deferred on purpose: loads SciPy's sparse graphs, SciPy's spatial only where used
        from scipy.spatial.transform import Rotation

        rvec = Rotation.from_matrix(Rm).as_rotvec()
    else:
        rvec = _matrix(fields["R"], (3,), f"{where} field 'R' (a rotation vector)")
    t = _matrix(fields["t"], (3,), f"{where} field 't'")
    return {"name": name, "size": (int(size[0]), int(size[1])), "fx": K[0, 0], "fy": K[1, 1],
            "cx": K[0, 2], "cy": K[1, 2], "skew": K[0, 1], "dist": dist, "rvec": rvec, "t": t}


def _read_toml(path: Path) -> dict:
    if not path.exists():
        raise UserError(f"{path}: no such rig file")
    try:
        with open(path, "rb") as handle:
            return tomllib.load(handle)
    except tomllib.TOMLDecodeError as exc:
        raise UserError(f"{path}: not valid TOML ({exc})") from None
    except OSError as exc:
        raise UserError(f"{path}: cannot read ({exc.strerror})") from None


def read_rig(path: str | Path) -> RigFields:
    """A rig.toml (or OpenCV YAML, by suffix) read and checked."""
    path = Path(path)
    if path.suffix.lower() in (".yaml", ".yml"):
        return import_opencv_yaml(path)
    doc = _read_toml(path)
    cams = doc.get("cameras")
    if not isinstance(cams, list) or not cams:
        raise UserError(f"{path}: no [[cameras]] tables: is this a rig file?")
    cameras = [camera_args(c, f"{path}:") for c in cams]
    names = [c["name"] for c in cameras]
    dupes = sorted({n for n in names if names.count(n) > 1})
    if dupes:
        raise UserError(f"{path}: camera name '{dupes[0]}' is used twice")
    quality = doc.get("quality", {})
    meta = doc.get("meta", {})
    return RigFields(cameras, dict(quality), dict(meta))


def _floats(a) -> list:
    return np.asarray(a, dtype=np.float64).tolist()


def camera_fields(cam: Camera) -> dict:
    """A camera as a TOML table: K as a matrix, R as a rotation vector."""
    return {
        "name": cam.name,
        "size": [cam.width, cam.height],
        "K": _floats(cam.K),
        "dist": _floats(cam.dist),
        "R": _floats(cam.rvec),
        "t": _floats(cam.t),
    }


def _toml_array(values) -> str:
    """A numeric (nested) array on one line; repr keeps every float's full precision."""
    if isinstance(values, (list, tuple)):
        return "[" + ", ".join(_toml_array(v) for v in values) + "]"
    return repr(int(values)) if isinstance(values, (int, np.integer)) else repr(float(values))


def _camera_toml(cam: Camera) -> str:
    f = camera_fields(cam)
    return "\n".join([
        "[[cameras]]",
        f"name = {_toml_string(cam.name)}",
        f"size = {_toml_array(f['size'])}  # width, height (px)",
        f"K = {_toml_array(f['K'])}  # [[fx, skew, cx], [0, fy, cy], [0, 0, 1]] (px)",
        f"dist = {_toml_array(f['dist'])}  # k1, k2, p1, p2, k3 (OpenCV)",
        f"R = {_toml_array(f['R'])}  # world-to-camera rotation vector (rad)",
        f"t = {_toml_array(f['t'])}  # world-to-camera translation (m)",
    ]) + "\n"


def _toml_string(text: str) -> str:
    # deferred on purpose: loads tomli_w only where used
    import tomli_w

    return tomli_w.dumps({"x": text}).split("=", 1)[1].strip()


def rig_to_toml(rig: Rig) -> str:
    """The rig as TOML: header, [meta], [quality], then one [[cameras]] table per camera
    with one line per field, so the file stays easy to read and to edit by hand."""
    # deferred on purpose: loads tomli_w only where used
    import tomli_w

    meta = {"created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")}
    meta.update({k: v for k, v in rig.meta.items() if v is not None})
    doc = {"format": FORMAT, "version": VERSION, "meta": _plain(meta)}
    if rig.quality:
        doc["quality"] = _plain(rig.quality)
    head = tomli_w.dumps(doc, multiline_strings=False)
    return head + "".join("\n" + _camera_toml(c) for c in rig.cameras)


def _plain(value):
    """Numpy scalars/arrays -> plain Python for TOML; drop None (TOML has no null)."""
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items() if v is not None}
    if isinstance(value, (list, tuple, np.ndarray)):
        return [_plain(v) for v in value]
    if isinstance(value, np.generic):
        return value.item()
    return value


def save_rig(rig: Rig, path: str | Path) -> None:
    path = Path(path)
    if path.suffix.lower() in (".yaml", ".yml"):
        export_opencv_yaml(rig, path)
        return
    write_text_atomic(path, rig_to_toml(rig))


# ---- OpenCV FileStorage YAML -------------------------------------------------------------

def export_opencv_yaml(rig: Rig, path: str | Path) -> None:
    """Write the rig as OpenCV FileStorage YAML (a sequence `cameras`), atomically."""
    # deferred on purpose: loads OpenCV only where used
    import cv2

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".yaml", dir=path.parent)
    os.close(fd)
    try:
        fs = cv2.FileStorage(tmp, cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_FORMAT_YAML)
        fs.startWriteStruct("cameras", cv2.FILE_NODE_SEQ)
        for cam in rig.cameras:
            fs.startWriteStruct("", cv2.FILE_NODE_MAP)
            fs.write("name", cam.name)
            fs.startWriteStruct("size", cv2.FILE_NODE_SEQ | cv2.FILE_NODE_FLOW)
            fs.write("", int(cam.width))
            fs.write("", int(cam.height))
            fs.endWriteStruct()
            fs.write("K", cam.K)
            fs.write("dist", cam.dist.reshape(1, 5))
            fs.write("R", cam.R)
            fs.write("t", cam.t.reshape(3, 1))
            fs.endWriteStruct()
        fs.endWriteStruct()
        fs.release()
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def import_opencv_yaml(path: str | Path) -> RigFields:
    """Read a rig from OpenCV FileStorage YAML as written by export_opencv_yaml."""
    # deferred on purpose: loads OpenCV only where used
    import cv2

    path = Path(path)
    if not path.exists():
        raise UserError(f"{path}: no such file")
    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except cv2.error:
        raise UserError(f"{path}: not an OpenCV FileStorage file") from None
    try:
        if not fs.isOpened():
            raise UserError(f"{path}: not an OpenCV FileStorage file")
        seq = fs.getNode("cameras")
        if seq.empty() or not seq.isSeq() or seq.size() == 0:
            raise UserError(f"{path}: no 'cameras' sequence: is this a rig file?")
        cameras = []
        for i in range(seq.size()):
            node = seq.at(i)
            name_node = node.getNode("name")
            name = name_node.string() if not name_node.empty() else ""
            fields = {"name": name or f"#{i}"}
            size_node = node.getNode("size")
            if not size_node.empty():
                fields["size"] = [size_node.at(j).real() for j in range(size_node.size())]
            for key in ("K", "dist", "R", "t"):
                mat = node.getNode(key)
                if not mat.empty():
                    value = mat.mat()
                    if value is None:
                        raise UserError(f"{path}: camera '{fields['name']}': field '{key}' "
                                        "is not a matrix")
                    fields[key] = value.tolist()
            cameras.append(camera_args(fields, f"{path}:"))
    finally:
        fs.release()
    return RigFields(cameras, {}, {"imported_from": str(path)})
