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


def _read_recording(path: Path) -> tuple[Observations, Truth | None]:
    with open(path, encoding="utf-8") as handle:
        first = handle.readline()
        try:
            header = json.loads(first)
        except json.JSONDecodeError:
            header = None
        if not isinstance(header, dict) or header.get("format") != FORMAT:
            raise UserError(f"{path}: not a calibkit recording (expected a '{FORMAT}' header)")
        if header.get("version", 0) > VERSION:
            raise UserError(f"{path}: recording version {header['version']} is newer than "
                            f"this calibkit reads ({VERSION}); upgrade calibkit")
        names = tuple(c["name"] for c in header["cameras"])
        sizes = tuple(tuple(c["size"]) for c in header["cameras"])
        frames, cams, times, counts, blobs, markers = [], [], [], [], [], []
        truth_f, truth_m, truth_xyz = [], [], []
        has_marker = True
        for lineno, line in enumerate(handle, start=2):
            try:
                rec = json.loads(line)
            except json.JSONDecodeError:
                # A torn last line (the process was killed mid-write) ends the recording;
                # a broken line followed by good ones means the file is damaged.
                if handle.readline():
                    raise UserError(f"{path}:{lineno}: damaged record") from None
                break
            if "truth" in rec:
                truth_f.append(np.full(len(rec["m"]), rec["truth"]))
                truth_m.append(rec["m"])
                truth_xyz.extend(rec["xyz"])
                continue
            b = rec["b"]
            frames.append(rec["f"])
            cams.append(rec["c"])
            times.append(rec["t"])
            counts.append(len(b))
            blobs.extend(b)
            if "m" in rec:
                markers.extend(rec["m"])
            else:
                has_marker = False
    counts = np.asarray(counts, dtype=np.int64)
    table = np.asarray(blobs, dtype=np.float64).reshape(-1, 4)
    cam = np.repeat(np.asarray(cams, dtype=np.int64), counts)
    if len(cam) and (cam.min() < 0 or cam.max() >= len(names)):
        raise UserError(f"{path}: a record names camera index {cam.max()}, "
                        f"but the header lists {len(names)} cameras")
    obs = Observations(
        names, sizes, np.repeat(np.asarray(frames, dtype=np.int64), counts), cam,
        np.repeat(np.asarray(times, dtype=np.int64), counts), table[:, :2], table[:, 2],
        table[:, 3], np.asarray(markers) if (has_marker and len(markers) == len(table)) else None,
        header.get("fps"), dict(header.get("meta") or {}))
    truth = None
    if truth_f:
        truth = Truth(np.concatenate(truth_f), np.concatenate(truth_m), np.asarray(truth_xyz))
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

def _csv_rows(path: Path, required: tuple[str, ...]) -> tuple[list[str], list[list[str]]]:
    if not path.exists():
        raise UserError(f"{path}: no such file")
    with open(path, encoding="utf-8", newline="") as handle:
        reader = csv.reader(handle)
        header = next(reader, None)
        if header is None:
            raise UserError(f"{path}: empty file; expected a header {','.join(required)}")
        header = [h.strip() for h in header]
        missing = [c for c in required if c not in header]
        if missing:
            raise UserError(f"{path}: line 1: missing column(s) {', '.join(missing)} "
                            f"(expected {','.join(required)})")
        rows = [row for row in reader if row and any(cell.strip() for cell in row)]
    for i, row in enumerate(rows):
        if len(row) != len(header):
            raise UserError(f"{path}: line {i + 2}: {len(row)} fields, the header has "
                            f"{len(header)}")
    return header, rows


def _column(path: Path, header: list[str], rows: list[list[str]], name: str, dtype):
    j = header.index(name)
    values = [row[j] for row in rows]
    try:
        return np.array(values, dtype=np.float64).astype(dtype) if dtype is not str else values
    except ValueError:
        for i, v in enumerate(values):
            try:
                float(v)
            except ValueError:
                raise UserError(f"{path}: line {i + 2}, column '{name}': {v!r} is not a "
                                "number") from None
        raise


def _read_csv(path: Path, rig=None) -> tuple[Observations, Truth | None]:
    header, rows = _csv_rows(path, CSV_COLUMNS)
    cam_names = _column(path, header, rows, "camera", str)
    if rig is not None:
        names = tuple(rig.names)
        sizes = tuple(c.size for c in rig)
        known = set(names)
        for i, n in enumerate(cam_names):
            if n not in known:
                raise UserError(f"{path}: line {i + 2}, column 'camera': camera '{n}' is not "
                                f"in the rig (it has {', '.join(names)})")
    else:
        names = tuple(dict.fromkeys(cam_names))
        sizes = tuple((0, 0) for _ in names)
    lookup = {n: i for i, n in enumerate(names)}
    camera = np.array([lookup[n] for n in cam_names], dtype=np.int32)
    marker = _column(path, header, rows, "marker", np.int64) if "marker" in header else None
    obs = Observations(
        names, sizes, _column(path, header, rows, "frame", np.int64), camera,
        _column(path, header, rows, "t_ns", np.int64),
        np.column_stack([_column(path, header, rows, "u", np.float64),
                         _column(path, header, rows, "v", np.float64)]),
        _column(path, header, rows, "area", np.float64),
        _column(path, header, rows, "peak", np.float64), marker)
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
    header, rows = _csv_rows(path, TRUTH_COLUMNS)
    xyz = np.column_stack([_column(path, header, rows, c, np.float64) for c in "xyz"])
    return Truth(_column(path, header, rows, "frame", np.int64),
                 _column(path, header, rows, "marker", np.int64), xyz)


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
