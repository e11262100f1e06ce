"""Reading and writing labelled marker takes (C3D, CSV) and unlabelled points.

Everything inside the program is in metres (the project's unit); C3D files are converted
from and to their POINT:UNITS (usually millimetres). A take is one array of shape
(frames, markers, 3) with NaN where a marker was not seen, so that labelling, gap filling
and the skeleton all work on plain numpy.
"""

from __future__ import annotations

import csv
import io
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from calibkit.core.errors import UserError
from calibkit.core.fileio import atomic_write, write_bytes_atomic

# BVH export lives in daemon/formats/bvh.py; its names stay importable from here, where
# the skeleton and the tests have always found them.
from daemon.formats.bvh import (  # noqa: F401
    euler_zxy_matrix,
    read_bvh,
    write_bvh,
    zxy_euler_deg,
)

UNIT_TO_M = {"mm": 1e-3, "cm": 1e-2, "m": 1.0, "dm": 0.1, "in": 0.0254}


@dataclass
class Take:
    """Labelled markers over time: xyz_m[frame, marker] in metres, NaN where not seen.

    `filled` marks samples that gap filling made up (True), so exports can say which
    samples were measured.
    """

    labels: list[str]
    xyz_m: np.ndarray
    rate_hz: float
    first_frame: int = 0
    filled: np.ndarray | None = None
    meta: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.xyz_m = np.asarray(self.xyz_m, dtype=np.float64)
        if self.xyz_m.ndim != 3 or self.xyz_m.shape[2] != 3 or \
                self.xyz_m.shape[1] != len(self.labels):
            raise ValueError(f"xyz_m must be (frames, {len(self.labels)}, 3), "
                             f"got {self.xyz_m.shape}")
        if self.filled is None:
            self.filled = np.zeros(self.xyz_m.shape[:2], dtype=bool)

    @property
    def n_frames(self) -> int:
        return self.xyz_m.shape[0]

    @property
    def visible(self) -> np.ndarray:
        return np.isfinite(self.xyz_m).all(axis=2)

    def index(self, label: str) -> int:
        return self.labels.index(label)

    def select(self, labels: list[str]) -> Take:
        """The same take restricted (and reordered) to `labels`."""
        idx = [self.index(name) for name in labels]
        return Take(list(labels), self.xyz_m[:, idx].copy(), self.rate_hz, self.first_frame,
                    self.filled[:, idx].copy(), dict(self.meta))


@dataclass
class Points:
    """Unlabelled 3D points: one row per point, with the frame it belongs to."""

    frame: np.ndarray   # (n,) int
    xyz_m: np.ndarray   # (n, 3)

    def frames(self) -> np.ndarray:
        return np.unique(self.frame)

    def split(self) -> tuple[np.ndarray, list[np.ndarray]]:
        """(frame numbers, list of (k_i, 3) point arrays), in frame order."""
        order = np.argsort(self.frame, kind="stable")
        f = self.frame[order]
        xyz = self.xyz_m[order]
        frames, starts = np.unique(f, return_index=True)
        return frames, np.split(xyz, starts[1:])

    @staticmethod
    def from_take(take: Take, seed: int = 0) -> Points:
        """Strip the labels of a take and shuffle the points within each frame."""
        rng = np.random.default_rng(seed)
        vis = take.visible
        fr, mk = np.nonzero(vis)
        key = fr + rng.random(len(fr))
        order = np.argsort(key)
        return Points(fr[order] + take.first_frame, take.xyz_m[fr[order], mk[order]])


# ---------------------------------------------------------------------------------- C3D


def _clean_label(raw: str) -> str:
    name = raw.strip()
    return name.split(":", 1)[1] if ":" in name else name


def read_c3d(path: str | Path, strip_prefix: bool = True) -> Take:
    """Read the points of a C3D file; analog data are ignored.

    Files whose header disagrees with their parameters only about the analog rate while
    holding no analog data (as CMU's 01_01.c3d: 1 sample per frame in the header, 600/120
    in ANALOG:RATE, no channels) are read as they are: the frame layout does not depend on
    that field. Any other inconsistency is reported as a UserError naming the file.
    """
    # deferred on purpose: loads c3d only where used
    import c3d

    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise UserError(f"cannot read {path}: {exc.strerror}") from None
    if len(data) < 512 or data[1] != 0x50:
        raise UserError(f"{path} is not a C3D file (no C3D header in its first 512 bytes)")

    class _Tolerant(c3d.Reader):
        def _check_metadata(self):
            try:
                super()._check_metadata()
            except AssertionError as exc:
                if "analog rate" in str(exc) and self._header.analog_count == 0 \
                        and self.analog_used == 0:
                    return  # the analog rate is irrelevant without analog samples
                raise

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            reader = _Tolerant(io.BytesIO(data))
            n_points = int(reader.point_used)
            n_frames = int(reader.last_frame) - int(reader.first_frame) + 1
            labels_raw = list(reader.point_labels)[:n_points]
            # a damaged header can claim billions of frames: never allocate more than the
            # file can hold (each point of a frame is at least 4 int16 values)
            if n_points < 0 or max(n_frames, 0) * n_points * 8 > len(data):
                raise UserError(f"{path}: truncated C3D file: the header says {n_frames} "
                                f"frames of {n_points} points, more than its "
                                f"{len(data)} bytes hold")
            xyz = np.full((max(n_frames, 0), n_points, 3), np.nan)
            filled = np.zeros((max(n_frames, 0), n_points), bool)
            i = -1
            for i, (_, pts, _) in enumerate(reader.read_frames(copy=False)):
                if i >= n_frames:
                    break
                ok = pts[:, 3] >= 0
                xyz[i, ok] = pts[ok, :3]
                filled[i] = pts[:, 3] == 0      # C3D: a residual of 0 marks a made-up sample
            units = "mm"
            try:
                units = reader.get_string("POINT:UNITS").strip().lower() or "mm"
            except Exception:  # noqa: BLE001 - the parameter is optional
                pass
            rate = float(reader.point_rate)
            first = int(reader.first_frame)
    except AssertionError as exc:
        raise UserError(f"{path}: inconsistent C3D header ({exc}); re-export the file") \
            from None
    except UserError:
        raise
    except Exception as exc:  # noqa: BLE001 - the c3d package trusts the file: a damaged
        # one fails anywhere inside it (IndexError, struct.error, UnboundLocalError, ...)
        raise UserError(f"{path}: unreadable C3D file ({type(exc).__name__}: "
                        f"{str(exc)[:80]})") from None
    if i + 1 < n_frames:
        raise UserError(f"{path}: truncated C3D file: {i + 1} of {n_frames} frames present")
    if not (np.isfinite(rate) and rate > 0):
        raise UserError(f"{path}: the C3D header's frame rate is {rate}, not a positive "
                        "number")
    scale = UNIT_TO_M.get(units)
    if scale is None:
        raise UserError(f"{path}: unknown POINT:UNITS {units!r} (expected mm, cm or m)")
    labels = [_clean_label(s) if strip_prefix else s.strip() for s in labels_raw]
    if len(labels) != n_points:
        raise UserError(f"{path}: {len(labels)} point labels for {n_points} points; "
                        "re-export the file")
    xyz *= scale
    # C3D files mark missing samples with a negative residual; some writers use zeros.
    zero = (xyz == 0).all(axis=2)
    xyz[zero] = np.nan
    filled &= ~zero
    if filled.sum() == np.isfinite(xyz).all(axis=2).sum():
        filled[:] = False    # every residual 0: the writer kept no residuals (85_02)
    return Take(labels, xyz, rate, first, filled, meta={"source": str(path)})


def write_c3d(path: str | Path, take: Take) -> None:
    """Write a take as a float C3D in millimetres; missing samples get residual -1.

    Measured samples get residual 1 (the residual is unknown here), filled ones 0: the
    C3D convention for interpolated samples, which read_c3d turns back into `filled`.
    """
    # deferred on purpose: loads c3d only where used; the frames written in one block
    from daemon.formats.c3d_write import c3d_bytes

    write_bytes_atomic(path, c3d_bytes(take))


# ---------------------------------------------------------------------------------- CSV


def _open_csv_rows(path: Path) -> tuple[list[str], list[list[str]]]:
    try:
        with open(path, newline="", encoding="utf-8") as handle:
            rows = [r for r in csv.reader(handle) if r and not r[0].startswith("#")]
    except OSError as exc:
        raise UserError(f"cannot read {path}: {exc.strerror}") from None
    except UnicodeDecodeError:
        raise UserError(f"{path} is not a text CSV file") from None
    if not rows:
        raise UserError(f"{path} is empty")
    return [h.strip().lower() for h in rows[0]], rows[1:]


def _columns(path: Path, header: list[str], need: list[str]) -> list[int]:
    missing = [c for c in need if c not in header]
    if missing:
        raise UserError(f"{path}: missing column(s) {', '.join(missing)}; expected a header "
                        f"with {','.join(need)} (got {','.join(header)})")
    return [header.index(c) for c in need]


def _points_csv_numpy(path: Path) -> Points | None:
    """The points through numpy's C reader (minutes of capture read in a blink), or None
    when it cannot take the file (no header, empty cells, text): the checking reader
    then names the problem."""
    try:
        with open(path, encoding="utf-8") as handle:
            skip, line = 0, ""
            for line in handle:
                skip += 1
                if not line.startswith("#"):
                    break
    except (OSError, UnicodeDecodeError):
        return None
    header = [h.strip().lower() for h in line.split(",")]
    if not all(c in header for c in ("frame", "x", "y", "z")):
        return None
    cols = [header.index(c) for c in ("frame", "x", "y", "z")]
    try:
        data = np.loadtxt(path, delimiter=",", comments="#", skiprows=skip, usecols=cols,
                          ndmin=2, dtype=np.float64)
    except ValueError:
        return None
    ok = np.isfinite(data[:, 1:]).all(axis=1)
    return Points(data[ok, 0].astype(np.int64), data[ok, 1:])


def read_points_csv(path: str | Path) -> Points:
    """Unlabelled points `frame,x,y,z[,...]` in metres, as `calibkit triangulate` writes."""
    path = Path(path)
    fast = _points_csv_numpy(path)
    if fast is not None:
        return fast
    header, rows = _open_csv_rows(path)
    cols = _columns(path, header, ["frame", "x", "y", "z"])
    try:
        arr = np.array([[float(r[c]) for c in cols] for r in rows], dtype=np.float64)
    except (ValueError, IndexError):
        raise UserError(f"{path}: a row has a missing or non-numeric frame/x/y/z value") \
            from None
    arr = arr.reshape(-1, 4)
    ok = np.isfinite(arr[:, 1:]).all(axis=1)
    return Points(arr[ok, 0].astype(np.int64), arr[ok, 1:])


def read_labelled_csv(path: str | Path, rate_hz: float | None = None) -> Take:
    """Labelled markers `frame,label,x,y,z[,filled]` in metres (one row per marker-frame)."""
    path = Path(path)
    header, rows = _open_csv_rows(path)
    cols = _columns(path, header, ["frame", "label", "x", "y", "z"])
    fcol = header.index("filled") if "filled" in header else None
    try:
        frames = np.array([int(float(r[cols[0]])) for r in rows], dtype=np.int64)
        names = [r[cols[1]].strip() for r in rows]
        xyz = np.array([[float(r[c]) for c in cols[2:]] for r in rows]).reshape(-1, 3)
        filled = np.array([r[fcol].strip() in ("1", "true", "True") for r in rows]) \
            if fcol is not None else np.zeros(len(rows), bool)
    except (ValueError, IndexError):
        raise UserError(f"{path}: a row has a missing or non-numeric value") from None
    if not rows:
        raise UserError(f"{path} has a header but no rows")
    labels = list(dict.fromkeys(names))
    li = {name: i for i, name in enumerate(labels)}
    first = int(frames.min())
    n_frames = int(frames.max()) - first + 1
    out = np.full((n_frames, len(labels), 3), np.nan)
    mk = np.array([li[n] for n in names])
    out[frames - first, mk] = xyz
    fill = np.zeros((n_frames, len(labels)), bool)
    fill[frames - first, mk] = filled
    rate = rate_hz
    if rate is None:
        rate = 120.0
        if "rate_hz" in header:
            rate = float(rows[0][header.index("rate_hz")])
    return Take(labels, out, rate, first, fill, meta={"source": str(path)})


def write_labelled_csv(path: str | Path, take: Take) -> None:
    """One row per seen (or filled) marker-frame: frame,label,x,y,z,filled (metres)."""
    vis = take.visible
    fr, mk = np.nonzero(vis)
    with atomic_write(path, "w", newline="", encoding="utf-8") as handle:
        handle.write(f"# rate_hz={take.rate_hz:g}\n")
        handle.write("frame,label,x,y,z,filled\n")
        xyz = take.xyz_m[fr, mk]
        lab = np.asarray(take.labels, dtype=object)[mk]
        filled = take.filled[fr, mk].astype(int)
        frames = fr + take.first_frame
        lines = [f"{f},{name},{x:.6f},{y:.6f},{z:.6f},{k}\n"
                 for f, name, (x, y, z), k in zip(frames, lab, xyz, filled, strict=True)]
        handle.writelines(lines)


def write_points_csv(path: str | Path, points: Points) -> None:
    with atomic_write(path, "w", newline="", encoding="utf-8") as handle:
        handle.write("frame,x,y,z\n")
        handle.writelines(f"{f},{x:.6f},{y:.6f},{z:.6f}\n"
                          for f, (x, y, z) in zip(points.frame, points.xyz_m, strict=True))


def csv_rate(path: Path) -> float | None:
    """The `# rate_hz=` comment our CSV writers put first, if there."""
    try:
        with open(path, encoding="utf-8") as handle:
            first = handle.readline()
    except (OSError, UnicodeDecodeError):
        return None
    if first.startswith("# rate_hz="):
        try:
            return float(first.split("=", 1)[1])
        except ValueError:
            return None
    return None


def read_take(path: str | Path, rate_hz: float | None = None) -> Take:
    """A labelled take from .c3d or .csv (chosen by suffix)."""
    path = Path(path)
    if not path.exists():
        raise UserError(f"{path} does not exist")
    suffix = path.suffix.lower()
    if suffix == ".c3d":
        return read_c3d(path)
    if suffix == ".csv":
        return read_labelled_csv(path, rate_hz or csv_rate(path))
    raise UserError(f"{path}: labelled takes are .c3d or .csv files, got {suffix or 'no suffix'}")


def write_take(path: str | Path, take: Take) -> None:
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".c3d":
        write_c3d(path, take)
    elif suffix == ".csv":
        write_labelled_csv(path, take)
    else:
        raise UserError(f"--out must end in .c3d or .csv, got {path.name}")


def read_points(path: str | Path) -> Points:
    """Unlabelled points from a CSV (frame,x,y,z,...) or a C3D (labels ignored)."""
    path = Path(path)
    if not path.exists():
        raise UserError(f"{path} does not exist")
    if path.suffix.lower() == ".c3d":
        return Points.from_take(read_c3d(path))
    if path.suffix.lower() == ".csv":
        return read_points_csv(path)
    raise UserError(f"{path}: unlabelled points are a .csv (frame,x,y,z) or .c3d file")
