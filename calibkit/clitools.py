"""What every command line shares: the user-error exit, option parsing, JSON output, progress
on stderr. Used by calibkit's and mocapd's commands alike."""

from __future__ import annotations

import importlib
import ipaddress
import json
import math
import sys
import time
from pathlib import Path

import numpy as np
import typer

from calibkit.core.camera import Rig
from calibkit.core.errors import UserError
from calibkit.core.fileio import write_text_atomic

EXIT_USER_ERROR = 2


def build_app(name: str, help_text: str, version: str, package: str,
              modules: tuple[str, ...]) -> typer.Typer:
    """A Typer app whose commands live in `package`, one module each with register(app),
    registered in the order given (the order of --help). A module not written yet is
    skipped; an import error inside a module is a bug and raises."""
    app = typer.Typer(name=name, help=help_text, no_args_is_help=True, add_completion=False,
                      pretty_exceptions_enable=False)

    def show_version(value: bool) -> None:
        if value:
            typer.echo(f"{name} {version}")
            raise typer.Exit()

    @app.callback()
    def _root(show: bool = typer.Option(False, "--version", callback=show_version,
                                        is_eager=True, help="Print the version and exit.")
              ) -> None:
        pass

    _root.__doc__ = help_text
    for module_name in modules:
        try:
            module = importlib.import_module(f"{package}.{module_name}")
        except ModuleNotFoundError as exc:
            if exc.name != f"{package}.{module_name}":
                raise
            continue
        module.register(app)
    return app


def run_app(app: typer.Typer, prog_name: str) -> None:
    """Run a Typer app; a UserError becomes one line on stderr and exit code 2."""
    try:
        app(prog_name=prog_name)
    except UserError as exc:
        print(f"{prog_name}: error: {exc}", file=sys.stderr)
        sys.exit(EXIT_USER_ERROR)
    except KeyboardInterrupt:
        print(f"{prog_name}: interrupted", file=sys.stderr)
        sys.exit(130)


def _jsonable(value):
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return _jsonable(value.tolist())
    if isinstance(value, np.generic):
        return _jsonable(value.item())
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, Path):
        return str(value)
    return value


def write_json(path: str | Path, data) -> None:
    """Write figures as JSON, atomically; NaN/inf become null so any parser reads it."""
    write_text_atomic(path, json.dumps(_jsonable(data), indent=2) + "\n")


def print_table(rows: list[list], header: list[str], file=None) -> None:
    """A plain aligned text table: numbers right-aligned, text left-aligned."""
    file = file or sys.stdout
    cells = [[format_cell(v) for v in row] for row in rows]
    widths = [max(len(h), *(len(r[i]) for r in cells)) if cells else len(h)
              for i, h in enumerate(header)]
    numeric = [all(isinstance(r[i], (int, float, np.number)) for r in rows) if rows else False
               for i in range(len(header))]

    def line(values):
        return "  ".join(v.rjust(w) if num else v.ljust(w)
                         for v, w, num in zip(values, widths, numeric, strict=True)).rstrip()

    print(line(header), file=file)
    print("  ".join("-" * w for w in widths), file=file)
    for r in cells:
        print(line(r), file=file)


def format_cell(v) -> str:
    """A table cell: floats to a few significant digits, NaN and inf as '-'."""
    if isinstance(v, (float, np.floating)):
        if not math.isfinite(v):
            return "-"
        a = abs(v)
        if a != 0 and (a < 1e-3 or a >= 1e6):
            return f"{v:.3g}"
        return f"{v:.3f}" if a < 100 else f"{v:.1f}"
    return str(v)


class Progress:
    """Progress of long work on stderr: a live line on a terminal, a line every few seconds
    otherwise (logs, CI), and always a final line."""

    def __init__(self, label: str, total: int | None = None, every_s: float = 2.0,
                 stream=None, enabled: bool = True) -> None:
        self.label, self.total, self.every_s = label, total, every_s
        self.stream = stream or sys.stderr
        self.enabled = enabled
        self.tty = hasattr(self.stream, "isatty") and self.stream.isatty()
        self.start = self.last = time.monotonic()
        self.done = 0

    def update(self, done: int, extra: str = "") -> None:
        self.done = done
        now = time.monotonic()
        if not self.enabled or (now - self.last < (0.2 if self.tty else self.every_s)):
            return
        self.last = now
        self._emit(extra, final=False)

    def finish(self, extra: str = "") -> None:
        if self.enabled:
            self._emit(extra, final=True)

    def _emit(self, extra: str, final: bool) -> None:
        elapsed = time.monotonic() - self.start
        of = f"/{self.total}" if self.total else ""
        pct = f" ({100 * self.done / self.total:.0f}%)" if self.total else ""
        text = f"{self.label}: {self.done}{of}{pct} {elapsed:.1f}s {extra}".rstrip()
        if self.tty:
            end = "\n" if final else ""
            print("\r\033[K" + text, end=end, file=self.stream, flush=True)
        else:
            print(text, file=self.stream, flush=True)


def parse_size(text: str) -> tuple[int, int]:
    """'640x480' -> (640, 480)."""
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise UserError(f"--size takes WIDTHxHEIGHT in pixels, like 640x480; got {text!r}") \
            from None
    if w < 16 or h < 16:
        raise UserError(f"--size must be at least 16x16 pixels, got {text!r}")
    return w, h


def parse_view(text: str) -> tuple[str, int]:
    """--view [HOST:]PORT -> (host, port), for every command that serves a page; a bare port
    is served on loopback only."""
    host, sep, port = text.rpartition(":")
    host = host.strip("[]") if sep else "127.0.0.1"
    try:
        ipaddress.ip_address(host)
        port_n = int(port)
        if not 0 < port_n < 65536:
            raise ValueError
    except ValueError:
        raise UserError(f"--view: expected [HOST:]PORT with HOST an IP address (127.0.0.1 "
                        f"for this computer only), got {text!r}") from None
    return host, port_n


def parse_floats(text: str, option: str) -> list[float]:
    """'0,0.2,0.5' -> [0.0, 0.2, 0.5]."""
    try:
        return [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise UserError(f"{option} takes numbers separated by commas, got {text!r}") from None


def load_rig_option(path: Path | None, option: str = "--rig") -> Rig:
    if path is None:
        raise UserError(f"{option} RIG.toml is required")
    return Rig.load(path)
