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
from typing import TYPE_CHECKING

import typer
from typer.core import TyperCommand, TyperGroup

from calibkit.core.errors import UserError
from calibkit.core.fileio import write_text_atomic

if TYPE_CHECKING:
    from calibkit.core.camera import Rig

# numpy, and everything that imports it, is imported inside the functions that need it, on
# purpose: this module is loaded by `calibkit --help` and `mocapd --help` (issue 31).

EXIT_USER_ERROR = 2

# Help and usage errors are drawn by click's plain formatter, not typer's rich panels: rich's
# help renderer imports markdown, syntax highlighting and emoji tables, about 0.15 s of every
# `--help` on a small machine (issue 31's target is 0.3 s for the whole command).
HELP_MARKUP = None


class LazyGroup(TyperGroup):
    """The top-level command group, loading a command's module only when that command runs
    or shows its own help. The commands' one-line summaries for the top-level help come from
    a static table (tests/test_cli_startup.py checks it against the real commands), so
    `calibkit --help` imports no command module, and `calibkit wand --help` only wand's."""

    package = ""
    table: dict[str, tuple[str, str]] = {}  # command name -> (module in package, short help)

    def __init__(self, **attrs) -> None:
        super().__init__(**attrs)
        self._loaded: dict[str, object] = {}  # name -> the real click command
        for name, (_module, help_text) in self.table.items():
            self.commands.setdefault(name, TyperCommand(name=name, help=help_text))

    def get_command(self, ctx, cmd_name: str):
        return self._loaded.get(cmd_name) or super().get_command(ctx, cmd_name)

    def resolve_command(self, ctx, args: list[str]):
        if args and args[0] in self.table:
            return args[0], self.load(args[0]), args[1:]
        return super().resolve_command(ctx, args)

    def load(self, cmd_name: str):
        """The real command: its module imported and registered on an app of its own."""
        if cmd_name not in self._loaded:
            module_name = self.table[cmd_name][0]
            module = importlib.import_module(f"{self.package}.{module_name}")
            holder = typer.Typer(add_completion=False, rich_markup_mode=HELP_MARKUP)
            holder.callback()(_no_options)
            module.register(holder)
            commands = typer.main.get_group(holder).commands
            for name, cmd in commands.items():
                if self.table.get(name, ("",))[0] == module_name:
                    self._loaded[name] = cmd
            if cmd_name not in self._loaded:
                raise RuntimeError(f"{self.package}.{module_name} registers no command "
                                   f"{cmd_name!r}; fix the command table")
        return self._loaded[cmd_name]


def _no_options() -> None:
    """A callback, so that a module registering a single command still makes a group."""


def build_app(name: str, help_text: str, version: str, package: str,
              commands: dict[str, tuple[str, str]]) -> typer.Typer:
    """A Typer app whose commands live in `package`, listed in `commands` (name -> (module,
    short help)) in the order of --help; each module has register(app) and is imported only
    when one of its commands is used (issue 31: `--help` must not pay for numpy, OpenCV,
    GTSAM...)."""
    group_class = type(f"{name.title()}Commands", (LazyGroup,),
                       {"package": package, "table": dict(commands)})
    app = typer.Typer(name=name, help=help_text, no_args_is_help=True, add_completion=False,
                      pretty_exceptions_enable=False, cls=group_class,
                      rich_markup_mode=HELP_MARKUP)

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
    return app


def eager_group(app: typer.Typer) -> TyperGroup:
    """The app's group with every command loaded (for tests that compare against the
    static table, and tools that list every command)."""
    group = typer.main.get_command(app)
    for cmd_name in list(group.table):
        group.load(cmd_name)
    return group


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
    import numpy as np

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
    import numpy as np

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
    import numpy as np

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
    from calibkit.core.camera import Rig

    return Rig.load(path)
