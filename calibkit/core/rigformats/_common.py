"""Checks and conversions every other tool's calibration reader shares: one clear line per mistake.

Other tools' files arrive hand-edited, half-calibrated or from a version we never saw, so
each value is checked where it is read and the error names the file, the camera and the
key as that tool spells it (`matrix`, not our `K`): the user fixes the file they have,
not ours. Readers build cameras only through `make_camera`, so every format gets the same
checks (finite numbers, a real rotation, positive focal lengths, a principal point inside
the image, a distortion model we can represent).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from calibkit.core.camera import Camera, Rig, rotation_from_rvec, rvec_from_rotation
from calibkit.core.errors import UserError

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib  # type: ignore[no-redef]

# A rotation matrix read from a file may carry only 6-7 significant digits (QTM writes
# some that way): accept |R R^T - I| up to this and snap to the nearest rotation.
ROTATION_TOLERANCE = 1e-4

UNITS_M = {"m": 1.0, "cm": 0.01, "mm": 0.001}


def read_bytes(path: Path) -> bytes:
    if not path.exists():
        raise UserError(f"{path}: no such file")
    if path.is_dir():
        raise UserError(f"{path}: is a folder; give the calibration file inside it")
    try:
        return path.read_bytes()
    except OSError as exc:
        raise UserError(f"{path}: cannot read ({exc.strerror})") from None


def load_toml(path: Path) -> dict:
    """A TOML file's tables; a syntax error is the user's, said in one line."""
    data = read_bytes(path)
    try:
        return tomllib.loads(data.decode("utf-8"))
    except UnicodeDecodeError:
        raise UserError(f"{path}: not a text file") from None
    except tomllib.TOMLDecodeError as exc:
        raise UserError(f"{path}: not valid TOML ({exc})") from None


def numbers(value, shape: tuple[int, ...], where: str) -> np.ndarray:
    """`value` as float64 of `shape`, finite; `where` starts the error message."""
    if value is None or isinstance(value, (str, bool, dict)):
        raise UserError(f"{where} must be numbers shaped {list(shape)}, got {value!r}")
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise UserError(f"{where} must be numbers shaped {list(shape)}, got {value!r}") \
            from None
    if arr.size != math.prod(shape):
        raise UserError(f"{where} must be {math.prod(shape)} numbers shaped {list(shape)}, "
                        f"got {arr.size}")
    if not np.all(np.isfinite(arr)):
        raise UserError(f"{where} holds a value that is not a finite number")
    return arr.reshape(shape)


def number(value, where: str) -> float:
    return float(numbers([value], (1,), where)[0])


def rotation_matrix(value, where: str) -> np.ndarray:
    """A 3x3 rotation; a matrix that is not one (scaled, mirrored, garbage) is refused."""
    R = numbers(value, (3, 3), where)
    if (np.max(np.abs(R @ R.T - np.eye(3))) > ROTATION_TOLERANCE
            or np.linalg.det(R) <= 0):
        raise UserError(f"{where} is not a rotation matrix (not orthonormal with "
                        "determinant +1)")
    u, _, vt = np.linalg.svd(R)  # snap the last digits to the nearest rotation
    return u @ vt


def rotation_vector(value, where: str) -> np.ndarray:
    """A rotation given as a Rodrigues vector (3 numbers) or a 3x3 matrix: the vector."""
    arr = np.asarray(value, dtype=object)
    if arr.size == 9:
        return rvec_from_rotation(rotation_matrix(value, where))
    rvec = numbers(value, (3,), f"{where} (a rotation vector or a 3x3 matrix)")
    if np.linalg.norm(rvec) > 4 * math.pi:
        raise UserError(f"{where} is a rotation vector of {np.linalg.norm(rvec):.1f} rad: "
                        "not a rotation")
    return rvec


def camera_matrix(value, where: str) -> np.ndarray:
    K = numbers(value, (3, 3), where)
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        raise UserError(f"{where} must have positive focal lengths, got fx={K[0, 0]:g}, "
                        f"fy={K[1, 1]:g}")
    if abs(K[1, 0]) > 1e-9 or np.max(np.abs(K[2] - [0.0, 0.0, 1.0])) > 1e-9:
        raise UserError(f"{where} must be [[fx, skew, cx], [0, fy, cy], [0, 0, 1]]")
    return K


def distortion(value, where: str) -> np.ndarray:
    """OpenCV coefficients k1 k2 p1 p2 [k3 [k4 k5 k6 ...]]: the first five, refusing a
    longer model whose extra terms are not zero (the rational and thin-prism models bend
    the image in ways five coefficients cannot)."""
    arr = np.asarray(value if value is not None else [], dtype=object).ravel()
    if arr.size < 4:
        raise UserError(f"{where} must hold at least 4 coefficients (k1, k2, p1, p2), "
                        f"got {arr.size}")
    dist = numbers(list(arr), (arr.size,), where)
    if dist.size > 5 and np.any(dist[5:] != 0):
        raise UserError(f"{where} has {dist.size} coefficients with non-zero k4.. terms: "
                        "only OpenCV's five-coefficient model (k1 k2 p1 p2 k3) is supported")
    out = np.zeros(5)
    out[: min(5, dist.size)] = dist[:5]
    return out


def image_size(value, where: str) -> tuple[int, int]:
    size = numbers(value, (2,), where)
    if np.any(size < 1) or np.any(size != np.round(size)):
        raise UserError(f"{where} must be two positive whole numbers [width, height], "
                        f"got {list(size)}")
    return int(size[0]), int(size[1])


def make_camera(name: str, size: tuple[int, int], K: np.ndarray, dist: np.ndarray,
                rvec: np.ndarray, t: np.ndarray, where: str) -> Camera:
    """A checked camera. The principal point must fall inside the image: a size written
    [height, width] by mistake (or read in the wrong order) shows up here."""
    w, h = size
    cx, cy = K[0, 2], K[1, 2]
    if not (-0.5 <= cx <= w - 0.5 and -0.5 <= cy <= h - 0.5):
        hint = (" (the size looks like [height, width])"
                if -0.5 <= cx <= h - 0.5 and -0.5 <= cy <= w - 0.5 else "")
        raise UserError(f"{where} principal point ({cx:g}, {cy:g}) lies outside the "
                        f"{w}x{h} image{hint}")
    return Camera(name, (w, h), K[0, 0], K[1, 1], cx, cy, K[0, 1], dist, rvec, t)


def make_rig(cameras: list[Camera], path: Path, fmt: str, meta: dict | None = None) -> Rig:
    if not cameras:
        raise UserError(f"{path}: no calibrated camera found in this {fmt} file")
    names = [c.name for c in cameras]
    dupes = sorted({n for n in names if names.count(n) > 1})
    if dupes:
        raise UserError(f"{path}: camera name '{dupes[0]}' is used twice")
    info = {"imported_from": str(path), "imported_format": fmt}
    info.update(meta or {})
    return Rig(tuple(cameras), meta=info)


def unit_m(unit: str) -> float:
    try:
        return UNITS_M[unit]
    except KeyError:
        raise UserError(f"unknown length unit {unit!r}: use one of "
                        f"{', '.join(UNITS_M)}") from None


def table_sort_key(key: str):
    """Natural order of table names (cam_2 before cam_10), as the tools list cameras."""
    digits = "".join(ch for ch in key if ch.isdigit())
    return (int(digits) if digits else math.inf, key)


def pose_matrix(cam: Camera) -> np.ndarray:
    return rotation_from_rvec(cam.rvec)


def floats(values) -> list:
    """Plain Python floats (nested) for a TOML writer; repr keeps every digit."""
    return np.asarray(values, dtype=np.float64).tolist()


def toml_value(value) -> str:
    """One TOML value on one line: numeric arrays stay readable and keep every digit."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, np.integer)):
        return repr(int(value))
    if isinstance(value, (float, np.floating)):
        return repr(float(value))
    if isinstance(value, (list, tuple, np.ndarray)):
        return "[" + ", ".join(toml_value(v) for v in value) + "]"
    if isinstance(value, str):
        # deferred on purpose: loads tomli_w only where a file is written
        import tomli_w

        return tomli_w.dumps({"x": value}).split("=", 1)[1].strip()
    raise TypeError(f"no TOML form for {type(value).__name__}")


def toml_key(key: str) -> str:
    return key if key and all(ch.isalnum() or ch in "-_" for ch in key) else toml_value(key)


def toml_tables(tables: list[tuple[str, dict]]) -> str:
    """Tables of one-line values, in the given order: [name] then `key = value` lines."""
    out = []
    for name, table in tables:
        out.append(f"[{name}]")
        out.extend(f"{toml_key(k)} = {toml_value(v)}" for k, v in table.items())
        out.append("")
    return "\n".join(out)
