"""A points CSV read for a command (track, label, markerset check): progress, bad rows said.

Why here: reading is the library's (daemon/formats/points_csv.py, which never prints); what
the user sees while it reads (a progress line for a big file on stderr, one warning line
counting the rows skipped, or with --strict one error line) is the same for every command
that takes points, so it is written once.
"""

from __future__ import annotations

import os
from pathlib import Path

import typer

from calibkit.clitools import Progress
from calibkit.core.errors import UserError

PROGRESS_FROM_BYTES = 64 << 20  # smaller files read in a blink: no progress line


def read_points_for_command(path: Path, strict: bool = False):
    """(Points, BadRows) of a points CSV; a warning line on stderr when rows were skipped.
    UserError (one line) for a file that cannot be read, or a bad row under `strict`."""
    from daemon.formats.points_csv import read_points_csv  # deferred: the handler's work

    def read(progress):
        points, bad = read_points_csv(path, strict, progress)
        return points, bad, len(points.frame)

    return _read(path, read)


def spool_points_for_command(path: Path, folder: Path, strict: bool = False):
    """(Spool, BadRows) of a points CSV: its points on disk in `folder`, for tracking in
    windows (daemon.analysis.track_stream); said as read_points_for_command says it, and a
    folder it cannot write in (or fill) said in one line too. The caller closes the
    spool."""
    from daemon.analysis.track_stream import Spool
    from daemon.formats.points_csv import stream_points_csv

    need_mb = os.path.getsize(path) // 1_000_000 + 1 if path.is_file() else 1
    try:
        spool = Spool(folder)
    except OSError as exc:
        raise UserError(f"cannot write a temporary file in {folder}: {exc.strerror}") \
            from None
    try:
        _, bad = _read(path, lambda progress: (
            spool, stream_points_csv(path, spool, strict, progress), spool.n))
        return spool.finish(), bad
    except OSError as exc:
        spool.close()
        raise UserError(f"cannot write the points to a temporary file in {folder}: "
                        f"{exc.strerror} (it needs up to about {need_mb} MB free)") from None
    except BaseException:
        spool.close()
        raise


def _read(path: Path, read):
    """read(progress) -> (what was read, BadRows, points), with the progress line and
    the warning."""
    size = os.path.getsize(path) if path.is_file() else 0
    reading = Progress(f"read {path.name} (MB)", max(size >> 20, 1),
                       enabled=size >= PROGRESS_FROM_BYTES)
    got, bad, n = read(lambda done, _: reading.update(done >> 20))
    reading.finish(f"{n} points")
    if bad.count:
        typer.echo(f"warning: {path}: {bad.summary()}; --strict refuses such a file",
                   err=True)
    return got, bad


def bad_rows_json(bad) -> dict:
    """The bad rows as the commands' --json figures carry them."""
    return {"rows": bad.rows, "skipped": bad.count, "by_kind": dict(bad.kinds),
            "first_line": bad.first_line}
