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

PROGRESS_FROM_BYTES = 64 << 20  # smaller files read in a blink: no progress line


def read_points_for_command(path: Path, strict: bool = False):
    """(Points, BadRows) of a points CSV; a warning line on stderr when rows were skipped.
    UserError (one line) for a file that cannot be read, or a bad row under `strict`."""
    from daemon.formats.points_csv import read_points_csv  # deferred: the handler's work

    size = os.path.getsize(path) if path.is_file() else 0
    reading = Progress(f"read {path.name} (MB)", max(size >> 20, 1),
                       enabled=size >= PROGRESS_FROM_BYTES)
    points, bad = read_points_csv(path, strict, lambda done, _: reading.update(done >> 20))
    reading.finish(f"{len(points.frame)} points")
    if bad.count:
        typer.echo(f"warning: {path}: {bad.summary()}; --strict refuses such a file",
                   err=True)
    return points, bad


def bad_rows_json(bad) -> dict:
    """The bad rows as the commands' --json figures carry them."""
    return {"rows": bad.rows, "skipped": bad.count, "by_kind": dict(bad.kinds),
            "first_line": bad.first_line}
