"""Reading other tools' wand data: DLTdv / Argus `xypts.csv` point files and easyWand profiles.

Both tools come from the same lab (Hedrick's DLTdv and easyWand; Argus writes the same files),
so the files share one pixel frame, which is not ours (docs/easywand.md):

- DLTdv is MATLAB: the first pixel's centre is (1, 1), and DLTdv 1-7 and Argus count y up
  from the bottom of the image (the frame is drawn with `axis xy`). Ours has pixel centres
  at integer coordinates from (0, 0) at the top left, y down. So u = x - 1 and
  v = height - y: the height must be known, which is what the camera profile (or a rig)
  gives. DLTdv 8 counts y down from the top (its users' converters say so); `y_origin="top"`
  reads those files (v = y - 1). Nothing in the file tells the two apart, so it is an option.
- easyWand subtracts the profile's principal point from the digitised points as they are,
  so the principal point is in the points' frame and converts the same way. Flipping y
  mirrors the lens model too: the tangential coefficient p1 changes sign, p2 does not.

An xypts file is one row per frame; per point, per camera, an X and a Y column (`pt1_cam1_X,
pt1_cam1_Y, pt1_cam2_X, ...`); NaN or an empty cell where a point was not digitised. The
point index is kept as the observation's `marker` (0 for pt1): these labels come from the
person or tracker who digitised the wand, so a wand's ends need no guessing.

Files arrive hand-edited and from versions we never saw, so readers take a header or none,
columns in any order, CRLF line ends and trailing commas, and every mistake ends in one
UserError naming the file and the line.
"""

from __future__ import annotations

import csv
import math
import re
from pathlib import Path

import numpy as np

from calibkit.core.camera import Camera, Rig
from calibkit.core.errors import UserError
from calibkit.core.observations import Observations

Y_ORIGINS = ("bottom", "top")
PROFILE_SOURCE = "easyWand camera profile"  # a rig's meta["source"] when read from one
NOMINAL_FPS = 100.0  # DLTdv files carry no times: t_ns counts frames at this rate unless told
PROFILE_MODELS = {0: "none", 1: "pinhole with radial and tangential distortion",
                  2: "fisheye"}
OUTSIDE_TOLERANCE = 0.01  # share of the image a digitised point may lie beyond its edge
_COLUMN = re.compile(r"^(?P<point>.+?)_cam_?(?P<camera>\d+)_(?P<axis>[xy])$", re.IGNORECASE)
_PT_NAME = re.compile(r"^pt(\d+)$", re.IGNORECASE)
_MISSING = {"", "nan", "-nan", "na", "n/a", "null"}
_FRAME_NAMES = {"frame", "frames", "frame_number", "frame number"}  # an optional column


def _check_origin(y_origin: str) -> None:
    if y_origin not in Y_ORIGINS:
        raise UserError(f"the y origin must be 'bottom' (DLTdv 1-7, Argus) or 'top' "
                        f"(DLTdv 8), got {y_origin!r}")


def _read_text(path: Path, what: str) -> str:
    if not path.exists():
        raise UserError(f"{path}: no such file")
    if path.is_dir():
        raise UserError(f"{path}: is a folder; give the {what} file")
    try:
        return path.read_bytes().decode("utf-8-sig")
    except UnicodeDecodeError:
        raise UserError(f"{path}: not a text file; expected {what}") from None
    except OSError as exc:
        raise UserError(f"{path}: cannot be read ({exc.strerror})") from None


def _is_number(cell: str) -> bool:
    text = cell.strip()
    if text.lower() in _MISSING:
        return True
    try:
        float(text)
    except ValueError:
        return False
    return True


# ---- the camera profile ---------------------------------------------------------------------

def _profile_rows(path: Path, text: str) -> list[tuple[int, list[float]]]:
    """(line number, values) of every camera row; blank lines, comments (# or %) and one
    header line before the first row are skipped."""
    rows: list[tuple[int, list[float]]] = []
    for lineno, line in enumerate(text.splitlines(), start=1):
        stripped = line.strip()
        if not stripped or stripped[0] in "#%":
            continue
        cells = [c for c in re.split(r"[,;\s]+", stripped) if c]
        try:
            values = [float(c) for c in cells]
        except ValueError:
            if not rows and not any(_is_number(c) for c in cells):
                continue  # a header line
            bad = next(c for c in cells if not _is_number(c))
            raise UserError(f"{path}: line {lineno}: {bad!r} is not a number (a camera "
                            "profile row is: camera number, focal length px, width, height, "
                            "principal point x, y, distortion model, 5 coefficients)") from None
        rows.append((lineno, values))
    return rows


def _profile_camera(path: Path, lineno: int, v: list[float], y_origin: str) -> Camera:
    where = f"{path}: line {lineno}"
    if len(v) < 6:
        raise UserError(f"{where}: {len(v)} values; a camera profile row needs at least 6: "
                        "camera number, focal length px, width, height, principal point x, y")
    if not all(math.isfinite(x) for x in v):
        raise UserError(f"{where}: holds a value that is not a finite number")
    number, f, w, h, ppx, ppy = v[:6]
    if number != round(number) or number < 0:
        raise UserError(f"{where}: the camera number must be a whole number, got {number:g}")
    if f <= 0:
        raise UserError(f"{where}: the focal length must be positive pixels, got {f:g}")
    if w != round(w) or h != round(h) or w < 1 or h < 1:
        raise UserError(f"{where}: width and height must be whole pixels, got {w:g} x {h:g}")
    if not (0 <= ppx <= w + 1 and 0 <= ppy <= h + 1):
        raise UserError(f"{where}: the principal point ({ppx:g}, {ppy:g}) is outside the "
                        f"{w:g} x {h:g} image: are the columns in easyWand's order (camera, "
                        "focal length, width, height, principal point x, y)?")
    model = 0
    coeffs = [0.0] * 5
    if len(v) > 6:
        if v[6] not in PROFILE_MODELS:
            raise UserError(f"{where}: distortion model {v[6]:g} is not one easyWand writes "
                            "(0 none, 1 pinhole with distortion, 2 fisheye)")
        model = int(v[6])
        given = v[7:12]
        extra = v[12:]
        if any(x != 0 for x in extra):
            raise UserError(f"{where}: {len(v)} values; a camera profile row has at most 12 "
                            "(camera, focal length, width, height, principal point x, y, "
                            "model, r2, r4, t1, t2, r6)")
        if model == 1 and len(given) < 5:
            raise UserError(f"{where}: distortion model 1 needs 5 coefficients (r2, r4, t1, "
                            f"t2, r6), the row has {len(given)}")
        if model == 0 and any(x != 0 for x in given):
            raise UserError(f"{where}: distortion model 0 (none) with non-zero coefficients; "
                            "set the model to 1 to use them, or zero them")
        if model == 2:
            raise UserError(f"{where}: camera {number:g} uses the fisheye model (2), which "
                            "calibkit's pinhole-and-OpenCV-distortion cameras cannot hold; "
                            "undistort its points first or calibrate it as a pinhole (1)")
        coeffs[:len(given)] = given
    k1, k2, t1, t2, k3 = coeffs
    if y_origin == "bottom":
        cy, t1 = h - ppy, 0.0 - t1  # y flipped: the tangential term along y changes sign
    else:
        cy = ppy - 1.0
    return Camera(f"cam{int(number)}", (int(w), int(h)), f, f, ppx - 1.0, cy, 0.0,
                  (k1, k2, t1, t2, k3))


def read_easywand_profile(path: str | Path, y_origin: str = "bottom") -> Rig:
    """An easyWand (or Argus) camera profile as a rig of intrinsics named cam1, cam2, ... by
    their camera numbers, converted to our pixel frame; no poses, no uncertainties."""
    _check_origin(y_origin)
    path = Path(path)
    rows = _profile_rows(path, _read_text(path, "easyWand camera profile"))
    if not rows:
        raise UserError(f"{path}: no camera rows; an easyWand camera profile has one row per "
                        "camera: camera number, focal length px, width, height, principal "
                        "point x, y[, distortion model, r2, r4, t1, t2, r6]")
    cams = [_profile_camera(path, lineno, v, y_origin) for lineno, v in rows]
    seen: dict[str, int] = {}
    for (lineno, _), cam in zip(rows, cams, strict=True):
        if cam.name in seen:
            raise UserError(f"{path}: line {lineno}: camera {cam.name[3:]} is listed twice "
                            f"(first on line {seen[cam.name]})")
        seen[cam.name] = lineno
    cams.sort(key=lambda c: int(c.name[3:]))
    return Rig(tuple(cams), meta={"source": PROFILE_SOURCE, "file": str(path),
                                  "y_origin": y_origin})


# ---- the xypts file -------------------------------------------------------------------------

def _csv_lines(path: Path, text: str) -> list[tuple[int, list[str]]]:
    """(line number, cells) of every line that holds anything. Lines are split first (CR, LF
    or CRLF), then read as CSV: numbers hold no line breaks."""
    out = []
    reader = csv.reader(text.splitlines())
    try:
        for lineno, cells in enumerate(reader, start=1):
            if any(c.strip() for c in cells):
                out.append((lineno, cells))
    except csv.Error as exc:
        raise UserError(f"{path}: line {reader.line_num}: not CSV ({exc})") from None
    return out


def _header_columns(path: Path, lineno: int, header: list[str]
                    ) -> tuple[list[str], list[int], np.ndarray, int | None]:
    """From a header: point names (in marker order), camera numbers (sorted), and per column
    its (point, camera, axis) indices, -1 for the frame column; and the frame column."""
    frame_col = None
    parsed: list[tuple[str, int, int]] = []
    for j, name in enumerate(header):
        if name.lower() in _FRAME_NAMES:
            if frame_col is not None:
                raise UserError(f"{path}: line {lineno}: two frame columns")
            frame_col = j
            parsed.append(("", -1, -1))
            continue
        m = _COLUMN.match(name)
        if m is None:
            raise UserError(f"{path}: line {lineno}: column {j + 1} is named {name!r}; a "
                            "DLTdv xypts header names every column like pt1_cam1_X, "
                            "pt1_cam1_Y, pt1_cam2_X, ...")
        parsed.append((m["point"], int(m["camera"]), 0 if m["axis"].lower() == "x" else 1))
    names = list(dict.fromkeys(p for p, _, _ in parsed if p))
    if not names:
        raise UserError(f"{path}: line {lineno}: no point columns (pt1_cam1_X, ...)")
    numbered = [_PT_NAME.match(n) for n in names]
    if all(numbered):
        names.sort(key=lambda n: int(_PT_NAME.match(n)[1]))
    cams = sorted({c for _, c, _ in parsed if c >= 0})
    point_of = {n: i for i, n in enumerate(names)}
    cam_of = {c: i for i, c in enumerate(cams)}
    index = np.full((len(header), 3), -1, dtype=np.int64)
    slots: dict[tuple[int, int, int], str] = {}
    for j, (p, c, a) in enumerate(parsed):
        if c < 0:
            continue
        key = (point_of[p], cam_of[c], a)
        if key in slots:
            raise UserError(f"{path}: line {lineno}: column {header[j]!r} appears twice")
        slots[key] = header[j]
        index[j] = key
    for p in range(len(names)):
        for c in range(len(cams)):
            for a, axis in enumerate("XY"):
                if (p, c, a) not in slots:
                    raise UserError(f"{path}: line {lineno}: no column "
                                    f"{names[p]}_cam{cams[c]}_{axis}; every point needs an X "
                                    "and a Y column for every camera")
    return names, cams, index, frame_col


def _trimmed(cells: list[str]) -> list[str]:
    """Cells without the empty ones a trailing comma leaves."""
    end = len(cells)
    while end and not cells[end - 1].strip():
        end -= 1
    return cells[:end]


def _numbers(path: Path, lines: list[tuple[int, list[str]]], header: list[str] | None,
             width: int) -> np.ndarray:
    """The data cells as floats (rows, width), NaN where not digitised; parsed as one array
    (a real capture is tens of thousands of rows)."""
    fitted = []
    for lineno, cells in lines:
        if len(cells) > width and not any(c.strip() for c in cells[width:]):
            cells = cells[:width]  # trailing commas
        if len(cells) != width:
            raise UserError(f"{path}: line {lineno}: {len(_trimmed(cells))} values, expected "
                            f"{width} ({'as the header has' if header else 'per frame'})")
        fitted.append((lineno, cells))
    lines = fitted
    if not lines:
        return np.zeros((0, width))
    try:  # the common file: numbers, NaN and empty cells
        flat = np.array([c or "nan" for _, row in lines for c in row], dtype=np.float64)
        return flat.reshape(len(lines), width)
    except ValueError:
        pass
    try:  # padded cells, NA, null...
        flat = np.array(["nan" if c.strip().lower() in _MISSING else c
                         for _, row in lines for c in row], dtype=np.float64)
        return flat.reshape(len(lines), width)
    except ValueError:
        for lineno, cells in lines:
            for j, c in enumerate(cells):
                if not _is_number(c):
                    column = f"column {header[j]!r}" if header else f"column {j + 1}"
                    raise UserError(f"{path}: line {lineno}, {column}: {c.strip()!r} is not "
                                    "a number") from None
        raise


def looks_like_xypts(path: str | Path) -> bool:
    """Whether a file's first line is a DLTdv xypts header, or a row of numbers (a file
    without a header): how `load_observations` tells it from our own files."""
    try:
        with open(path, encoding="utf-8-sig", errors="replace") as handle:
            first = ""
            for line in handle:
                if line.strip().strip(","):
                    first = line
                    break
    except OSError:
        return False
    cells = [c.strip() for c in first.strip().split(",")]
    while cells and cells[-1] == "":
        cells.pop()
    if not cells:
        return False
    if all(_COLUMN.match(c) or c.lower() in _FRAME_NAMES for c in cells):
        return True
    return len(cells) >= 4 and all(_is_number(c) for c in cells)


def _cameras_of(path: Path, cam_numbers: list[int], rig: Rig | None):
    """The rig camera behind each camera number of the file, or None without a rig.

    An easyWand profile's cameras are DLTdv's by number (camN is the file's camera N); any
    other rig (calibkit's cam0, cam1, ...) is the file's cameras in order, as is a profile
    numbered otherwise with as many cameras."""
    if rig is None:
        return None
    names = set(rig.names)
    from_profile = rig.meta.get("source") == PROFILE_SOURCE
    if from_profile and all(f"cam{c}" in names for c in cam_numbers):
        return [rig[f"cam{c}"] for c in cam_numbers]
    if len(rig) == len(cam_numbers) and not (
            from_profile and any(f"cam{c}" in names for c in cam_numbers)):
        return list(rig)
    raise UserError(f"{path}: cameras {', '.join(f'cam{c}' for c in cam_numbers)} do not match "
                    f"the {len(rig)} cameras of the profile or rig ({', '.join(rig.names)}); "
                    "give the easyWand profile the file was digitised with")


def read_xypts(path: str | Path, rig: Rig | None = None, y_origin: str = "bottom",
               fps: float | None = None, n_cameras: int | None = None) -> Observations:
    """A DLTdv / Argus xypts file as observations in our pixel frame.

    rig: the cameras (an easyWand profile read by read_easywand_profile, or a rig file):
    their names and image sizes; the height is needed to turn y-up pixels down, and the
    camera count to read a file without a header. Camera N of the file is the profile's
    camera N, or a rig's N-th camera. Frames are DLTdv's: the first data row is
    frame 1. fps: the capture rate, when known (t_ns counts frames at it, else at
    NOMINAL_FPS and fps stays unknown).
    """
    _check_origin(y_origin)
    if fps is not None and not (math.isfinite(fps) and fps > 0):
        raise UserError(f"the frame rate must be positive, got {fps}")
    path = Path(path)
    lines = _csv_lines(path, _read_text(path, "DLTdv xypts"))
    if not lines:
        raise UserError(f"{path}: empty file; expected DLTdv xypts rows (pt1_cam1_X, ...)")
    first_no, first = lines[0]
    first = _trimmed(first)
    header = None if all(_is_number(c) for c in first) else [c.strip() for c in first]
    if header is not None:
        names, cam_numbers, index, frame_col = _header_columns(path, first_no, header)
        data_lines = lines[1:]
        width = len(header)
    else:
        n_cams = n_cameras if n_cameras is not None else (len(rig) if rig is not None else None)
        if n_cams is None or n_cams < 1:
            raise UserError(f"{path}: no header, so the number of cameras is unknown; give "
                            "the camera profile (--profile)")
        # the width: a whole number of points, as long as the longest row once trailing
        # commas go, and no longer than the rows with them (the last point may be empty)
        longest = max(len(cells) for _, cells in lines)
        filled = max(len(_trimmed(cells)) for _, cells in lines)
        width = longest - longest % (2 * n_cams)
        if width < filled or width == 0:
            raise UserError(f"{path}: line {first_no}: {len(first)} values is not a whole "
                            f"number of points for {n_cams} cameras (2 values per camera per "
                            "point)")
        n_pts = width // (2 * n_cams)
        names = [f"pt{p + 1}" for p in range(n_pts)]
        cam_numbers = list(range(1, n_cams + 1))
        j = np.arange(width)
        index = np.stack([j // (2 * n_cams), (j // 2) % n_cams, j % 2], axis=1)
        frame_col = None
        data_lines = lines
    cams = _cameras_of(path, cam_numbers, rig)
    if cams is None and y_origin == "bottom":
        raise UserError(f"{path}: DLTdv counts y up from the image's bottom, so the image "
                        "heights are needed: give the camera profile (--profile) or a rig")
    table = _numbers(path, data_lines, header, width)
    n_rows, n_pts, n_cams = len(table), len(names), len(cam_numbers)
    if frame_col is not None:
        frame_of_row = table[:, frame_col]
        if not np.all(np.isfinite(frame_of_row) & (frame_of_row == np.round(frame_of_row))):
            raise UserError(f"{path}: the frame column must hold whole numbers")
        frame_of_row = frame_of_row.astype(np.int64)
        if len(np.unique(frame_of_row)) != n_rows:
            raise UserError(f"{path}: the frame column names a frame twice")
    else:
        frame_of_row = np.arange(1, n_rows + 1, dtype=np.int64)
    # dense (rows, points, cameras, 2) from the columns, wherever they sit
    xy = np.full((n_rows, n_pts, n_cams, 2), np.nan)
    cols = np.flatnonzero(index[:, 0] >= 0)
    xy[:, index[cols, 0], index[cols, 1], index[cols, 2]] = table[:, cols]
    seen = np.isfinite(xy).all(axis=3)
    row, pt, cam = np.nonzero(seen)
    order = np.lexsort((pt, cam, row))  # by frame, camera, then the wand's end
    row, pt, cam = row[order], pt[order], cam[order]
    x, y = xy[row, pt, cam, 0], xy[row, pt, cam, 1]
    if cams is not None:
        size = np.array([c.size for c in cams], dtype=np.float64).reshape(-1, 2)
        _check_inside(path, x, y, size[cam], data_lines, row, cam_numbers, cam)
        height = size[cam, 1]
        names_out = tuple(c.name for c in cams)
        sizes_out = tuple(c.size for c in cams)
    else:
        height = np.zeros(len(row))
        names_out = tuple(f"cam{c}" for c in cam_numbers)
        sizes_out = tuple((0, 0) for _ in cam_numbers)
    v = height - y if y_origin == "bottom" else y - 1.0
    uv = np.column_stack([x - 1.0, v])
    period_ns = 1e9 / (fps or NOMINAL_FPS)
    frame = frame_of_row[row]
    first_frame = int(frame_of_row.min()) if n_rows else 1
    t_ns = np.round((frame - first_frame) * period_ns).astype(np.int64)
    n = len(row)
    return Observations(
        names_out, sizes_out, frame, cam, t_ns, uv, np.zeros(n), np.zeros(n), pt, fps,
        {"source": "DLTdv xypts", "file": str(path), "y_origin": y_origin,
         "frames": "instants",  # a row is one instant for every camera (DLTdv's offsets applied)
         "points": names, "cameras": [f"cam{c}" for c in cam_numbers],
         "marker": "the digitised point index (pt1 = 0), not a simulator's truth"})


def _check_inside(path: Path, x, y, size, lines, row, cam_numbers, cam) -> None:
    """A point far outside its camera's image means the profile (or rig) is not this
    file's: another resolution, or the cameras in another order."""
    w, h = size[:, 0], size[:, 1]
    margin_w, margin_h = OUTSIDE_TOLERANCE * w + 1.0, OUTSIDE_TOLERANCE * h + 1.0
    bad = (x < 1 - margin_w) | (x > w + margin_w) | (y < 1 - margin_h) | (y > h + margin_h)
    if np.any(bad):
        k = int(np.flatnonzero(bad)[0])
        raise UserError(f"{path}: line {lines[row[k]][0]}: camera {cam_numbers[cam[k]]}'s point "
                        f"({x[k]:g}, {y[k]:g}) is outside its {w[k]:g} x {h[k]:g} image: is "
                        "the profile this file's, with the cameras in the same order?")
