"""Reading a points CSV (frame,x,y,z,...) of any size in bounded memory, counting bad rows.

Why: `calibkit triangulate` and other tools write one row per 3D point, so an hour of
capture is a gigabyte of text. Reading it whole (Python lists of floats, or the whole text
at once) costs several times the file in memory before a frame is tracked. Here the file is
read in blocks of whole lines; each block is checked with numpy on its bytes (blank and
comment lines, the comma count of every line against the header's) and parsed by numpy's C
reader; only a block holding text where a number should be is re-read in small pieces to
find the bad lines. Memory is the output arrays (32 bytes a point) plus one block.

A row that cannot be used (a value that is not a number or is empty, NaN or inf, a frame
that is not a whole number, more or fewer columns than the header) is not silently
dropped: it is counted by kind with the first one's line number, for the command to warn
about in one line, or refused at once (`strict`). The header is read first
(`points_header`), so a question about it (which frame rate?) is asked before the long read.
The points go to arrays (`read_points_csv`) or, a block at a time, to any sink
(`stream_points_csv`: `mocapd track` spools them to disk and tracks them in windows).
"""

from __future__ import annotations

import csv
import io
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from calibkit.core.errors import UserError
from daemon.formats.c3dio import Points

NEEDED = ("frame", "x", "y", "z")
BLOCK_BYTES = 8 << 20  # lines read at once: bounded memory, numpy's reader kept busy
PIECE_LINES = 2048  # a block with text in it is re-read in pieces of this many lines
NOT_A_NUMBER, NOT_FINITE, COLUMNS, FRAME = ("not a number", "NaN or inf",
                                            "wrong number of columns",
                                            "frame not a whole number")


@dataclass(frozen=True)
class PointsHeader:
    """What the lines before the data say: the columns, where the data start (byte offset
    and 1-based line number), and the frame rate a `# rate_hz=` comment gives."""

    columns: list[str]
    used: tuple[int, int, int, int]  # column indices of frame, x, y, z
    data_offset: int
    data_line: int
    rate_hz: float | None


@dataclass
class BadRows:
    """Rows that could not be used: how many of each kind, and the first one's line."""

    rows: int = 0  # data rows read, good and bad
    kinds: dict[str, int] = field(default_factory=dict)
    first_line: int | None = None
    first_kind: str = ""

    @property
    def count(self) -> int:
        return sum(self.kinds.values())

    def add(self, kind: str, line_numbers: np.ndarray) -> None:
        if not len(line_numbers):
            return
        self.kinds[kind] = self.kinds.get(kind, 0) + len(line_numbers)
        first = int(np.min(line_numbers))
        if self.first_line is None or first < self.first_line:
            self.first_line, self.first_kind = first, kind

    def summary(self) -> str:
        """For the user: how many rows were skipped, why, and the first."""
        kinds = ", ".join(f"{n} {k}" for k, n in sorted(self.kinds.items(),
                                                         key=lambda kv: -kv[1]))
        return (f"skipped {self.count} of {self.rows} rows ({kinds}); the first at line "
                f"{self.first_line} ({self.first_kind})")


def points_header(path: str | Path) -> PointsHeader:
    """The header of a points CSV, read without touching its data."""
    path = Path(path)
    rate = None
    offset = 0
    try:
        with open(path, "rb") as handle:
            for number, raw in enumerate(handle, 1):
                offset += len(raw)
                text = raw.decode("utf-8").lstrip("\ufeff").strip()  # a BOM: Excel's CSV
                if text.startswith("#"):
                    if text.replace(" ", "").startswith("#rate_hz="):
                        rate = _rate(path, text.split("=", 1)[1])
                    continue
                if not text:
                    continue
                header = [h.strip().lower() for h in next(csv.reader([text]))]
                missing = [c for c in NEEDED if c not in header]
                if missing:
                    raise UserError(f"{path}: missing column(s) {', '.join(missing)}; "
                                    f"expected a header with {','.join(NEEDED)} (got "
                                    f"{','.join(header)})")
                used = tuple(header.index(c) for c in NEEDED)
                return PointsHeader(header, used, offset, number + 1, rate)
    except OSError as exc:
        raise UserError(f"cannot read {path}: {exc.strerror}") from None
    except UnicodeDecodeError:
        raise UserError(f"{path} is not a text CSV file") from None
    raise UserError(f"{path} is empty: a points CSV starts with a header "
                    f"{','.join(NEEDED)}")


def _rate(path: Path, text: str) -> float:
    try:
        rate = float(text)
    except ValueError:
        rate = float("nan")
    if not np.isfinite(rate) or rate <= 0:
        raise UserError(f"{path}: its '# rate_hz=' comment gives {text.strip()!r}, not a "
                        "positive frame rate")
    return rate


def read_points_csv(path: str | Path, strict: bool = False, progress=None,
                    block_bytes: int = BLOCK_BYTES) -> tuple[Points, BadRows]:
    """Every usable point of the file and the rows that were not. With `strict` the first
    bad row ends the read with a UserError naming it. progress(bytes read, file size) is
    called after each block."""
    size = os.path.getsize(path) if Path(path).is_file() else 0
    out = _Growing(max(1024, size // 24))
    bad = stream_points_csv(path, out, strict, progress, block_bytes)
    frame, xyz = out.arrays()
    return Points(frame, xyz), bad


def stream_points_csv(path: str | Path, sink, strict: bool = False, progress=None,
                      block_bytes: int = BLOCK_BYTES) -> BadRows:
    """Every usable point of the file handed to sink.put(frame (n,), xyz (n, 3)) a block
    at a time, in the file's order; the rows that were not usable are returned. A file
    with no usable point is a UserError. With `strict` the first bad row ends the read
    with a UserError naming it. progress(bytes read, file size) is called after each
    block."""
    path = Path(path)
    head = points_header(path)
    size = os.path.getsize(path)
    out = _Counting(sink)
    bad = BadRows()
    line = head.data_line
    with open(path, "rb") as handle:
        handle.seek(head.data_offset)
        carry = b""
        while True:
            block = handle.read(block_bytes)
            data = carry + block
            if block:
                cut = data.rfind(b"\n") + 1
                data, carry = data[:cut], data[cut:]
            elif data and not data.endswith(b"\n"):
                data += b"\n"
            if data:
                _block(data, line, head, out, bad)
                line += data.count(b"\n")
            if strict and bad.count:
                raise UserError(f"{path}: line {bad.first_line}: {bad.first_kind} in frame, "
                                "x, y or z (--strict refuses such rows; without it they are "
                                "skipped and counted)")
            if progress is not None:
                progress(handle.tell() - len(carry), size)
            if not block:
                break
    if not out.n:
        if bad.count:
            raise UserError(f"{path}: holds no usable points: {bad.summary()}")
        raise UserError(f"{path}: holds no points")
    return bad


class _Counting:
    """A sink that counts the points it passes on."""

    def __init__(self, sink) -> None:
        self.sink, self.n = sink, 0

    def put(self, frame: np.ndarray, xyz: np.ndarray) -> None:
        if len(frame):
            self.sink.put(frame, xyz)
            self.n += len(frame)


class _Growing:
    """Output arrays filled block by block; grown (rarely) when the size guessed from the
    file's length was short. Pages never written cost no memory."""

    def __init__(self, capacity: int) -> None:
        self.frame = np.empty(capacity, np.int64)
        self.xyz = np.empty((capacity, 3))
        self.n = 0

    def put(self, frame: np.ndarray, xyz: np.ndarray) -> None:
        end = self.n + len(frame)
        if end > len(self.frame):
            grown = max(end, int(1.5 * len(self.frame)))
            for name in ("frame", "xyz"):
                old = getattr(self, name)
                new = np.empty((grown,) + old.shape[1:], old.dtype)
                new[:self.n] = old[:self.n]
                setattr(self, name, new)
        self.frame[self.n:end] = frame
        self.xyz[self.n:end] = xyz
        self.n = end

    def arrays(self) -> tuple[np.ndarray, np.ndarray]:
        return self.frame[:self.n], self.xyz[:self.n]


def _block(data: bytes, line0: int, head: PointsHeader, out: _Growing, bad: BadRows) -> None:
    """One block of whole lines (line0: the first one's number) into `out`."""
    buf = np.frombuffer(data, np.uint8)
    ends = np.flatnonzero(buf == 10)
    starts = np.concatenate([[0], ends[:-1] + 1])
    length = ends - starts
    first = np.where(length > 0, buf[np.minimum(starts, len(buf) - 1)], 0)
    blank = (length == 0) | ((length == 1) & (first == 13))
    data_line = ~blank & (first != ord("#"))
    commas = _per_line(np.flatnonzero(buf == ord(",")), ends)
    quoted = _per_line(np.flatnonzero(buf == ord('"')), ends) > 0
    wrong = data_line & (commas != len(head.columns) - 1) & ~quoted
    numbers = line0 + np.arange(len(ends))
    bad.rows += int(data_line.sum())
    if quoted.any():  # a quoted field may hold commas: this block line by line, in order
        _by_line(data, starts, ends, np.flatnonzero(data_line), numbers, head, out, bad)
        return
    bad.add(COLUMNS, numbers[wrong])
    plain = data_line & ~wrong & ~quoted
    if not plain.any():
        return
    if plain.sum() < data_line.sum():  # blank out the lines dealt with: numpy skips them
        copy = buf.copy()
        copy[starts[data_line & ~plain]] = ord("#")
        data = copy.tobytes()
    rows = np.flatnonzero(plain)
    try:
        values = _parse(data, head)
    except ValueError:  # text where a number should be: find it piece by piece
        for a in range(0, len(rows), PIECE_LINES):
            piece = rows[a:a + PIECE_LINES]
            text = b"".join(data[starts[i]:ends[i] + 1] for i in piece)
            try:
                _keep(_parse(text, head), numbers[piece], out, bad)
            except ValueError:
                _by_line(data, starts, ends, piece, numbers, head, out, bad)
        return
    _keep(values, numbers[rows], out, bad)


def _per_line(positions: np.ndarray, ends: np.ndarray) -> np.ndarray:
    """How many of the sorted byte `positions` fall on each line (lines end at `ends`):
    a few small arrays, never one the size of the block."""
    return np.diff(np.searchsorted(positions, ends), prepend=0)


def _parse(data: bytes, head: PointsHeader) -> np.ndarray:
    """numpy's C reader on the lines of `data`: (rows, 4) frame x y z."""
    return np.loadtxt(io.BytesIO(data), delimiter=",", comments="#", usecols=head.used,
                      ndmin=2, dtype=np.float64)  # bytes: no text copy 4 bytes a character


def _keep(values: np.ndarray, numbers: np.ndarray, out: _Growing, bad: BadRows) -> None:
    """Parsed rows (with their line numbers) into `out`, the unusable ones counted."""
    frame = values[:, 0]
    finite = np.isfinite(values).all(axis=1)
    whole = np.isfinite(frame) & (frame == np.round(frame)) & (np.abs(frame) < 2.0 ** 53)
    bad.add(NOT_FINITE, numbers[~finite])
    bad.add(FRAME, numbers[finite & ~whole])
    ok = finite & whole
    out.put(frame[ok].astype(np.int64), values[ok, 1:])


def _by_line(data: bytes, starts, ends, lines: np.ndarray, numbers, head: PointsHeader,
             out: _Growing, bad: BadRows) -> None:
    """The given lines parsed one at a time (the rare lines with text or quotes)."""
    width = len(head.columns)
    values, kept, not_number, columns = [], [], [], []
    for i in lines:  # only lines numpy could not take: a few per bad row
        text = data[starts[i]:ends[i]].decode("utf-8", errors="replace").rstrip("\r")
        fields = next(csv.reader([text]))
        if len(fields) != width:
            columns.append(numbers[i])
            continue
        try:
            values.append([float(fields[c]) for c in head.used])
            kept.append(numbers[i])
        except ValueError:
            not_number.append(numbers[i])
    bad.add(COLUMNS, np.array(columns, np.int64))
    bad.add(NOT_A_NUMBER, np.array(not_number, np.int64))
    if values:
        _keep(np.array(values), np.array(kept, np.int64), out, bad)

