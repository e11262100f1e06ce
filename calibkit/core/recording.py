"""Recordings of 2D observations (our `.mcrec` format) and the plain CSV files other tools share.

The recording is JSON lines: a header line, then one line per (frame, camera) with its blobs,
and truth lines for simulated captures (docs/formats.md). Lines are appended as frames
arrive and flushed, so a recording whose process was killed is read up to its last complete
line; a torn final line is ignored, nothing else is lost.
"""

from __future__ import annotations

import csv
import io
import json
import os
from pathlib import Path

import numpy as np

from calibkit.core import easywand
from calibkit.core.errors import UserError
from calibkit.core.fileio import atomic_write
from calibkit.core.observations import Observations, Truth

FORMAT = "calibkit-recording"
VERSION = 1
CSV_COLUMNS = ("frame", "camera", "t_ns", "u", "v", "area", "peak")
TRUTH_COLUMNS = ("frame", "marker", "x", "y", "z")


def truth_path_for(path: str | Path) -> Path:
    """`points.csv` -> `points.truth.csv`: where a CSV's ground truth sits."""
    path = Path(path)
    return path.with_name(path.stem + ".truth.csv")


# ---- our recording format ----------------------------------------------------------------

class RecordingWriter:
    """Appends frames to a `.mcrec` recording as they are captured.

    Every record is one line, flushed when written, so a killed process leaves a file that
    reads up to the last complete frame. Use as a context manager or call close().
    """

    def __init__(self, path: str | Path, camera_names, camera_sizes, fps: float | None = None,
                 meta: dict | None = None) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.camera_names = tuple(camera_names)
        header = {
            "format": FORMAT, "version": VERSION,
            "cameras": [{"name": n, "size": [int(s[0]), int(s[1])]}
                        for n, s in zip(self.camera_names, camera_sizes, strict=True)],
            "fps": fps, "meta": meta or {},
        }
        self._handle = open(self.path, "w", encoding="utf-8")  # noqa: SIM115 (kept open)
        self._write(header)

    def _write(self, record: dict) -> None:
        self._handle.write(json.dumps(record, separators=(",", ":")) + "\n")
        self._handle.flush()

    def append(self, frame: int, camera: int | str, t_ns: int, uv, area=None, peak=None,
               marker=None) -> None:
        """One camera's blobs of one frame; `camera` is an index or a name."""
        if isinstance(camera, str):
            camera = self.camera_names.index(camera)
        uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
        n = len(uv)
        area = np.zeros(n) if area is None else np.asarray(area, dtype=np.float64).reshape(n)
        peak = np.zeros(n) if peak is None else np.asarray(peak, dtype=np.float64).reshape(n)
        blobs = np.column_stack([np.round(uv, 4), np.round(area, 2), np.round(peak, 1)])
        record = {"f": int(frame), "c": int(camera), "t": int(t_ns), "b": blobs.tolist()}
        if marker is not None:
            record["m"] = np.asarray(marker, dtype=np.int64).reshape(n).tolist()
        self._write(record)

    def append_observations(self, obs: Observations) -> None:
        """All rows of `obs`, grouped into one record per (frame, camera)."""
        obs = obs.sorted()
        if len(obs) == 0:
            return
        key = obs.frame * (len(self.camera_names) + 1) + obs.camera
        starts = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
        ends = np.r_[starts[1:], len(obs)]
        for s, e in zip(starts, ends, strict=True):
            self.append(obs.frame[s], obs.camera[s], obs.t_ns[s], obs.uv[s:e], obs.area[s:e],
                        obs.peak[s:e], None if obs.marker is None else obs.marker[s:e])

    def append_truth(self, frame: int, marker, xyz) -> None:
        xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
        self._write({"truth": int(frame),
                     "m": np.asarray(marker, dtype=np.int64).reshape(len(xyz)).tolist(),
                     "xyz": np.round(xyz, 9).tolist()})

    def close(self) -> None:
        if not self._handle.closed:
            self._handle.flush()
            os.fsync(self._handle.fileno())
            self._handle.close()

    def __enter__(self) -> RecordingWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _header(path: Path, first: bytes) -> dict:
    """The header line, checked: a recording's cameras (names, sizes) and rate."""
    try:
        header = json.loads(first)
    except ValueError:  # JSON's errors and undecodable bytes alike
        header = None
    if not isinstance(header, dict) or header.get("format") != FORMAT:
        raise UserError(f"{path}: not a calibkit recording (expected a '{FORMAT}' header)")
    version, cams, fps = header.get("version", 0), header.get("cameras"), header.get("fps")
    if not _is_int(version):
        raise UserError(f"{path}:1: the header's version is not a number: {version!r}")
    if version > VERSION:
        raise UserError(f"{path}: recording version {version} is newer than "
                        f"this calibkit reads ({VERSION}); upgrade calibkit")
    if not isinstance(cams, list) or not all(
            isinstance(c, dict) and isinstance(c.get("name"), str)
            and isinstance(c.get("size"), list) and len(c["size"]) == 2
            and all(_is_int(v) and 0 <= v < 2 ** 31 for v in c["size"]) for c in cams):
        raise UserError(f"{path}:1: the header's cameras are not a list of "
                        "{\"name\": text, \"size\": [width, height]}")
    if fps is not None and not (_is_number(fps) and np.isfinite(fps) and fps > 0):
        raise UserError(f"{path}:1: the header's fps is not a positive number: {fps!r}")
    if not isinstance(header.get("meta") or {}, dict):
        raise UserError(f"{path}:1: the header's meta is not a table")
    return header


def _is_int(v) -> bool:
    return type(v) is int and -2 ** 63 <= v < 2 ** 63


def _is_number(v) -> bool:
    return type(v) in (int, float)


def _record_problem(rec, n_cams: int) -> str | None:
    """What is wrong with one record's shape and types (None: nothing). The blobs' and
    positions' values are checked for all records at once afterwards."""
    if not isinstance(rec, dict):
        return "not a JSON object"
    if "truth" in rec:
        m, xyz = rec.get("m"), rec.get("xyz")
        if not _is_int(rec["truth"]) or not isinstance(m, list) or not isinstance(xyz, list):
            return 'a truth record needs "truth" (frame), "m" (markers) and "xyz"'
        if len(m) != len(xyz) or not all(_is_int(k) for k in m):
            return 'a truth record needs one marker number in "m" per position in "xyz"'
        return None
    missing = [k for k in ("f", "c", "t", "b") if k not in rec]
    if missing:
        return f"a blobs record needs \"{missing[0]}\""
    if not (_is_int(rec["f"]) and _is_int(rec["c"]) and _is_int(rec["t"])):
        return 'frame "f", camera "c" and time "t" must be whole numbers'
    if not 0 <= rec["c"] < n_cams:
        return f"camera index {rec['c']}: the header lists {n_cams} cameras"
    if not isinstance(rec["b"], list):
        return 'blobs "b" must be a list'
    m = rec.get("m")
    if m is not None and (not isinstance(m, list) or len(m) != len(rec["b"])
                          or not all(_is_int(k) for k in m)):
        return '"m" needs one marker number per blob'
    return None


def _rows(path: Path, values: list, width: int, lines: list[int], counts, what: str):
    """`values` (lists of `width` numbers, counts[i] of them from line lines[i]) as one
    float array; the first line with a wrong or non-finite one named otherwise."""
    try:
        table = np.array(values, dtype=np.float64).reshape(-1, width)
        ok = len(table) == len(values) and bool(np.isfinite(table).all())
    except (ValueError, TypeError, OverflowError):
        ok, table = False, None
    if ok:
        return table
    for k, v in enumerate(values):  # only for a broken file: find where
        if not (isinstance(v, list) and len(v) == width
                and all(_is_number(x) and abs(x) < 1e300 for x in v)):
            line = lines[int(np.searchsorted(np.cumsum(counts), k, side="right"))]
            raise UserError(f"{path}:{line}: {what} {str(v)[:60]} is not {width} finite "
                            "numbers")
    raise UserError(f"{path}: {what} that are not numbers")  # not reached


def _read_recording(path: Path) -> tuple[Observations, Truth | None]:
    """A recording, every record checked: a malformed one ends with one line naming the
    file, the line and what is wrong; a torn last line (a killed writer) is skipped."""
    with open(path, "rb") as handle:
        header = _header(path, handle.readline())
        names = tuple(c["name"] for c in header["cameras"])
        sizes = tuple(tuple(c["size"]) for c in header["cameras"])
        frames, cams, times, counts, blobs, markers, lines = [], [], [], [], [], [], []
        truth_f, truth_m, truth_xyz, truth_lines, truth_counts = [], [], [], [], []
        has_marker = True
        for lineno, line in enumerate(handle, start=2):
            try:
                rec = json.loads(line)
            except ValueError:  # JSON's errors and undecodable bytes alike
                # A torn last line (the process was killed mid-write) ends the recording;
                # a broken line followed by good ones means the file is damaged.
                if handle.readline():
                    raise UserError(f"{path}:{lineno}: damaged record") from None
                break
            problem = _record_problem(rec, len(names))
            if problem is not None:
                raise UserError(f"{path}:{lineno}: malformed record ({problem})")
            if "truth" in rec:
                truth_f.append(np.full(len(rec["m"]), rec["truth"]))
                truth_m.append(rec["m"])
                truth_xyz.extend(rec["xyz"])
                truth_lines.append(lineno)
                truth_counts.append(len(rec["m"]))
                continue
            b = rec["b"]
            frames.append(rec["f"])
            cams.append(rec["c"])
            times.append(rec["t"])
            counts.append(len(b))
            lines.append(lineno)
            blobs.extend(b)
            if "m" in rec:
                markers.extend(rec["m"])
            else:
                has_marker = False
    counts = np.asarray(counts, dtype=np.int64)
    table = _rows(path, blobs, 4, lines, counts, "a blob (u, v, area, peak)")
    cam = np.repeat(np.asarray(cams, dtype=np.int64), counts)
    obs = Observations(
        names, sizes, np.repeat(np.asarray(frames, dtype=np.int64), counts), cam,
        np.repeat(np.asarray(times, dtype=np.int64), counts), table[:, :2], table[:, 2],
        table[:, 3], np.asarray(markers) if (has_marker and len(markers) == len(table)) else None,
        header.get("fps"), dict(header.get("meta") or {}))
    truth = None
    if truth_f:
        xyz = _rows(path, truth_xyz, 3, truth_lines, truth_counts, "a truth position")
        truth = Truth(np.concatenate(truth_f), np.concatenate(truth_m), xyz)
    return obs, truth


def _write_recording(path: Path, obs: Observations, truth: Truth | None) -> None:
    tmp = path.with_name(f".{path.name}.tmp")
    try:
        with RecordingWriter(tmp, obs.camera_names, obs.camera_sizes, obs.fps,
                             obs.meta) as writer:
            writer.append_observations(obs)
            if truth is not None and len(truth):
                order = np.argsort(truth.frame, kind="stable")
                t = truth.select(order)
                starts = np.flatnonzero(np.r_[True, t.frame[1:] != t.frame[:-1]])
                for s, e in zip(starts, np.r_[starts[1:], len(t)], strict=True):
                    writer.append_truth(t.frame[s], t.marker[s:e], t.xyz[s:e])
        os.replace(tmp, path)
    except BaseException:
        if tmp.exists():
            tmp.unlink()
        raise


# ---- plain CSV -----------------------------------------------------------------------------

def _csv_rows(path: Path, required: tuple[str, ...]):
    """(header, rows, each row's line number): blank rows left out, every row as wide as
    the header."""
    if not path.exists():
        raise UserError(f"{path}: no such file")
    with open(path, encoding="utf-8", newline="") as handle:
        reader = csv.reader(handle)
        try:
            header = next(reader, None)
            if header is None:
                raise UserError(f"{path}: empty file; expected a header "
                                f"{','.join(required)}")
            header = [h.strip() for h in header]
            missing = [c for c in required if c not in header]
            if missing:
                raise UserError(f"{path}: line 1: missing column(s) {', '.join(missing)} "
                                f"(expected {','.join(required)})")
            rows, lines = [], []
            for row in reader:
                if row and any(cell.strip() for cell in row):
                    rows.append(row)
                    lines.append(reader.line_num)
        except UnicodeDecodeError:
            raise UserError(f"{path}: line {reader.line_num + 1}: not UTF-8 text; a CSV of "
                            "observations is text") from None
        except csv.Error as exc:  # a field over the csv module's limit, a NUL byte...
            raise UserError(f"{path}: line {reader.line_num}: {exc}") from None
    for i, row in enumerate(rows):
        if len(row) != len(header):
            raise UserError(f"{path}: line {lines[i]}: {len(row)} fields, the header has "
                            f"{len(header)}")
    return header, rows, lines


def _column(path: Path, table, name: str, dtype):
    """One column of _csv_rows' table: text, whole numbers (exact: a t_ns of 1.7e18 keeps
    its last digits; 12.0 is 12) or finite numbers; a cell that is not names its line."""
    header, rows, lines = table
    j = header.index(name)
    values = [row[j] for row in rows]
    if dtype is str:
        return values
    whole = dtype is np.int64
    if whole:
        try:
            return np.array(values, dtype=np.int64)
        except (ValueError, OverflowError):
            pass
    try:
        column = np.array(values, dtype=np.float64)
        if np.isfinite(column).all() and (not whole or (
                (column == np.round(column)).all() and (np.abs(column) < 2 ** 53).all())):
            return column.astype(dtype)
    except ValueError:
        pass
    for i, v in enumerate(values):  # only for a broken file: find where
        try:
            x = float(v)
            ok = np.isfinite(x) and (not whole or (x == round(x) and abs(x) < 2 ** 53))
            if whole and not ok:  # digits beyond float's: exact as an integer
                ok = -2 ** 63 <= int(v) < 2 ** 63
        except (ValueError, OverflowError):
            ok = False
        if not ok:
            kind = "a whole number" if whole else "a finite number"
            raise UserError(f"{path}: line {lines[i]}, column '{name}': {v[:40]!r} is not "
                            f"{kind}")
    raise UserError(f"{path}: column '{name}' holds values that are not numbers")


def _read_csv(path: Path, rig=None) -> tuple[Observations, Truth | None]:
    table = header, rows, lines = _csv_rows(path, CSV_COLUMNS)
    cam_names = _column(path, table, "camera", str)
    if rig is not None:
        names = tuple(rig.names)
        sizes = tuple(c.size for c in rig)
        known = set(names)
        for i, n in enumerate(cam_names):
            if n not in known:
                raise UserError(f"{path}: line {lines[i]}, column 'camera': camera '{n}' is not "
                                f"in the rig (it has {', '.join(names)})")
    else:
        names = tuple(dict.fromkeys(cam_names))
        sizes = tuple((0, 0) for _ in names)
    lookup = {n: i for i, n in enumerate(names)}
    camera = np.array([lookup[n] for n in cam_names], dtype=np.int32)
    marker = _column(path, table, "marker", np.int64) if "marker" in header else None
    obs = Observations(
        names, sizes, _column(path, table, "frame", np.int64), camera,
        _column(path, table, "t_ns", np.int64),
        np.column_stack([_column(path, table, "u", np.float64),
                         _column(path, table, "v", np.float64)]),
        _column(path, table, "area", np.float64),
        _column(path, table, "peak", np.float64), marker)
    truth_file = truth_path_for(path)
    truth = load_truth_csv(truth_file) if truth_file.exists() else None
    return obs, truth


def _csv_text(obs: Observations) -> str:
    obs = obs.sorted()
    buf = io.StringIO()
    cols = list(CSV_COLUMNS) + (["marker"] if obs.marker is not None else [])
    buf.write(",".join(cols) + "\n")
    names = np.asarray(obs.camera_names, dtype=object)[obs.camera] if len(obs) else []
    for i in range(len(obs)):  # file output, not a hot path
        row = (f"{obs.frame[i]},{names[i]},{obs.t_ns[i]},{obs.uv[i, 0]:.4f},"
               f"{obs.uv[i, 1]:.4f},{obs.area[i]:.2f},{obs.peak[i]:.1f}")
        if obs.marker is not None:
            row += f",{obs.marker[i]}"
        buf.write(row + "\n")
    return buf.getvalue()


def load_truth_csv(path: str | Path) -> Truth:
    path = Path(path)
    table = _csv_rows(path, TRUTH_COLUMNS)
    xyz = np.column_stack([_column(path, table, c, np.float64) for c in "xyz"])
    return Truth(_column(path, table, "frame", np.int64),
                 _column(path, table, "marker", np.int64), xyz)


def save_truth_csv(path: str | Path, truth: Truth) -> None:
    order = np.lexsort((truth.marker, truth.frame))
    t = truth.select(order)
    with atomic_write(path, "w", encoding="utf-8") as handle:
        handle.write(",".join(TRUTH_COLUMNS) + "\n")
        for f, m, (x, y, z) in zip(t.frame, t.marker, t.xyz, strict=True):
            handle.write(f"{f},{m},{x:.9f},{y:.9f},{z:.9f}\n")


# ---- the two entry points ------------------------------------------------------------------

def save_observations(path: str | Path, obs: Observations, truth: Truth | None = None,
                      rig=None) -> None:
    """Write observations (and truth) by the path's suffix: `.csv` plain CSV (truth beside it
    as NAME.truth.csv), anything else our recording. Atomic: no half-written file."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.suffix.lower() == ".csv":
        with atomic_write(path, "w", encoding="utf-8") as handle:
            handle.write(_csv_text(obs))
        if truth is not None:
            save_truth_csv(truth_path_for(path), truth)
    else:
        _write_recording(path, obs, truth)


def load_observations(path: str | Path, rig=None) -> tuple[Observations, Truth | None]:
    """Read a recording, a plain CSV, or a DLTdv/easyWand xypts file (told apart by its
    first line; calibkit.core.easywand, y up from the bottom as DLTdv 1-7 and Argus write
    it). With a rig, the CSV's camera names are checked against it and the cameras' sizes
    taken from it; an xypts file needs one (an easyWand profile read into a rig will do)."""
    path = Path(path)
    if not path.exists():
        raise UserError(f"{path}: no such file")
    if path.is_dir():
        raise UserError(f"{path}: is a folder; give a recording (.mcrec) or a .csv file")
    if easywand.looks_like_xypts(path):
        return easywand.read_xypts(path, rig), None
    if path.suffix.lower() == ".csv":
        return _read_csv(path, rig)
    obs, truth = _read_recording(path)
    if rig is not None:
        missing = [n for n in obs.camera_names if n not in set(rig.names)]
        if missing:
            raise UserError(f"{path}: camera '{missing[0]}' of the recording is not in the rig "
                            f"(it has {', '.join(rig.names)})")
    return obs, truth
