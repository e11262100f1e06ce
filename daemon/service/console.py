"""What the mocapd commands print for a person: tables and progress, drawn with rich.

Why rich and not hand-drawn text: it is already installed (typer depends on it), it sizes
columns to the terminal and draws a live progress bar where there is one. Off a terminal
(a pipe, a log, a test) the same information goes out as plain lines: a table at its
natural width (never folded to 80 columns, so each row stays one line a script can read)
and a progress line every few seconds, with always a last one.
"""

from __future__ import annotations

import sys
import time

import numpy as np
from rich import box
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, TaskProgressColumn, TextColumn
from rich.progress import Progress as RichProgress
from rich.table import Table

from calibkit.clitools import format_cell
from daemon.process.logs import writes_to_journal

WIDE = 10_000  # off a terminal: wide enough that no table is folded


def console(file=None) -> Console:
    file = file or sys.stdout
    tty = hasattr(file, "isatty") and file.isatty()
    return Console(file=file, width=None if tty else WIDE, highlight=False,
                   soft_wrap=not tty)


cell = format_cell  # the same cells as calibkit's plain tables


def print_table(rows: list[list], header: list[str], file=None) -> None:
    """Rows under a header: numeric columns right-aligned, text left-aligned."""
    table = Table(box=box.SIMPLE_HEAD, show_edge=False, pad_edge=False, expand=False)
    for i, name in enumerate(header):
        numeric = bool(rows) and all(isinstance(r[i], (int, float, np.number)) for r in rows)
        table.add_column(name, justify="right" if numeric else "left", no_wrap=True)
    for r in rows:
        table.add_row(*(cell(v) for v in r))
    console(file).print(table)


class Progress:
    """Progress of long work on stderr: a rich bar on a terminal; otherwise a line every
    `every_s` seconds (logs, CI; priority info on the journal); always a final line."""

    def __init__(self, label: str, total: int | None = None, every_s: float = 2.0,
                 stream=None) -> None:
        self.label, self.total, self.every_s = label, total, every_s
        self.stream = stream or sys.stderr
        self.start = self.last = time.monotonic()
        self.done = 0
        self.prefix = "<6>" if writes_to_journal(self.stream) else ""  # info, on the journal
        self.bar = None
        if hasattr(self.stream, "isatty") and self.stream.isatty():
            self.bar = RichProgress(TextColumn("{task.description}"), BarColumn(),
                                    MofNCompleteColumn(), TaskProgressColumn(),
                                    TextColumn("{task.elapsed:.1f}s {task.fields[extra]}"),
                                    console=Console(file=self.stream), transient=False)
            self.task = self.bar.add_task(label, total=total, extra="")
            self.bar.start()

    def update(self, done: int, extra: str = "") -> None:
        self.done = done
        if self.bar is not None:
            self.bar.update(self.task, completed=done, extra=extra)
            return
        now = time.monotonic()
        if now - self.last >= self.every_s:
            self.last = now
            self._line(extra)

    def finish(self, extra: str = "") -> None:
        if self.bar is not None:
            self.bar.update(self.task, completed=self.done, extra=extra)
            self.bar.stop()
            return
        self._line(extra)

    def _line(self, extra: str) -> None:
        of = f"/{self.total}" if self.total else ""
        pct = f" ({100 * self.done / self.total:.0f}%)" if self.total else ""
        text = f"{self.label}: {self.done}{of}{pct} {time.monotonic() - self.start:.1f}s"
        print(f"{self.prefix}{text} {extra}".rstrip(), file=self.stream, flush=True)
