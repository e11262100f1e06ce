"""Other tools' calibration files read into a Rig, and the TOML ones written back.

One module per format (caliscope, pose2sim, anipose, qca; OpenCV YAML lives in
calibkit.core.rigfile). `detect_format` tells them apart by content, not by file name:
people rename files, and QTM's exports end in `.txt`.
"""

from __future__ import annotations

from pathlib import Path

from calibkit.core.camera import Camera, Rig
from calibkit.core.errors import UserError
from calibkit.core.rigfile import export_opencv_yaml, import_opencv_yaml
from calibkit.core.rigformats import _camtables, anipose, caliscope, pose2sim, qca
from calibkit.core.rigformats._common import UNITS_M, load_toml, read_bytes

READABLE = ("opencv", "caliscope", "pose2sim", "anipose", "qca")
WRITABLE = ("opencv", "caliscope", "pose2sim", "anipose")
KNOWN = "caliscope, Pose2Sim, anipose, QTM .qca, OpenCV YAML"


def detect_format(path: str | Path) -> str:
    """The format of a calibration file, from what it holds: one of READABLE, or
    "calibkit" for our own rig.toml."""
    path = Path(path)
    data = read_bytes(path)
    if qca.looks_like(data):
        return "qca"
    if data.lstrip().startswith(b"%YAML") or path.suffix.lower() in (".yaml", ".yml"):
        return "opencv"
    if data.lstrip().startswith(b"<"):
        raise UserError(f"{path}: an XML file but not a QTM calibration (no <calibration> "
                        "with <cameras>); calibkit reads " + KNOWN)
    try:
        doc = load_toml(path)
    except UserError:
        raise UserError(f"{path}: not a calibration file calibkit recognises (reads {KNOWN}; "
                        "the file is none of TOML, XML or OpenCV YAML)") from None
    if doc.get("format") == "calibkit-rig":
        return "calibkit"
    if caliscope.looks_like(doc):
        return "caliscope"
    if _camtables.looks_like(doc):
        # aniposelib names its tables cam_0, cam_1, ... and writes `fisheye` only on fisheye
        # cameras (= true); Pose2Sim names tables after the cameras (cam_01, int_cam01_img)
        # and writes `fisheye = false` on every one
        tables = _camtables.camera_tables(doc)
        positional = sorted(tables, key=lambda k: (len(k), k)) == [
            f"cam_{i}" for i in range(len(tables))]
        pinhole_marked = any(t.get("fisheye") is False for t in tables.values())
        return "anipose" if positional and not pinhole_marked else "pose2sim"
    raise UserError(f"{path}: a TOML file but not a calibration calibkit recognises (reads "
                    f"{KNOWN}); give --format if it is one of them")


def read_rig_file(path: str | Path, fmt: str = "auto",
                  unit: str = anipose.DEFAULT_UNIT) -> tuple[Rig, str]:
    """A calibration file of format `fmt` ("auto" detects it) as a Rig, and the format
    read. `unit` is the length unit of anipose files, which do not say it."""
    path = Path(path)
    if fmt == "auto":
        fmt = detect_format(path)
    if fmt == "calibkit":
        return Rig.load(path), fmt
    if fmt == "opencv":
        found = import_opencv_yaml(path)
        return Rig(tuple(Camera(**c) for c in found.cameras), quality=found.quality,
                   meta={**found.meta, "imported_format": "opencv"}), fmt
    if unit not in UNITS_M:
        raise UserError(f"--unit {unit!r}: use one of {', '.join(UNITS_M)}")
    readers = {"caliscope": caliscope.read_caliscope, "pose2sim": pose2sim.read_pose2sim,
               "anipose": lambda p: anipose.read_anipose(p, unit), "qca": qca.read_qca}
    if fmt not in readers:
        raise UserError(f"--format {fmt!r}: use auto or one of {', '.join(READABLE)}")
    return readers[fmt](path), fmt


def write_rig_file(rig: Rig, path: str | Path, fmt: str,
                   unit: str = anipose.DEFAULT_UNIT) -> None:
    """The rig written atomically as `fmt` (one of WRITABLE)."""
    if unit not in UNITS_M:
        raise UserError(f"--unit {unit!r}: use one of {', '.join(UNITS_M)}")
    writers = {"opencv": export_opencv_yaml, "caliscope": caliscope.write_caliscope,
               "pose2sim": pose2sim.write_pose2sim,
               "anipose": lambda r, p: anipose.write_anipose(r, p, unit)}
    if fmt not in writers:
        raise UserError(f"--format {fmt!r}: export writes one of {', '.join(WRITABLE)} "
                        "(QTM files come from QTM)")
    writers[fmt](rig, Path(path))
