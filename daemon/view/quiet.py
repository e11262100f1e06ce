"""The view process's log under bad requests: one line per kind a minute, no tracebacks.

Why: the view is a web server (viser on websockets), and whatever can reach its port can
send it junk: port scanners, old browser tabs of another viser version, fuzzers. Left
alone, websockets logs every failed handshake and every connection whose messages do not
decode with a full traceback, viser prints a line per rejected version to stdout and
tracebacks of failing callbacks to stderr: 428 bad connections once gave 3300 lines and
329 tracebacks in the daemon's journal (issue 30). Here every record that carries an
exception, and every record of a library's logger, is cut to one line (the exception's
type and message) and said once per kind a minute; what the libraries print to stdout and
stderr goes the same way. Also the checks of values that come from the page: a crafted
websocket message can put anything in a widget's value.
"""

from __future__ import annotations

import io
import logging
import math
import re
import sys
import threading
import time

from calibkit.core.errors import UserError

INTERVAL_S = 60.0
_VARYING = re.compile(r"'[^']*'|\"[^\"]*\"|0x[0-9a-f]+|\d+", re.IGNORECASE)


class _Limiter:
    """When each kind was last said; how many of it were held back since."""

    def __init__(self, interval_s: float) -> None:
        self.interval_s = interval_s
        self.said: dict[str, float] = {}
        self.held: dict[str, int] = {}
        self.lock = threading.Lock()

    def allow(self, kind: str) -> int | None:
        """None: hold this one back; else how many of its kind were held back before it."""
        now = time.monotonic()
        with self.lock:
            if now - self.said.get(kind, -1e18) < self.interval_s:
                self.held[kind] = self.held.get(kind, 0) + 1
                return None
            self.said[kind] = now
            return self.held.pop(kind, 0)


def _kind(text: str) -> str:
    """A line with its varying parts (numbers, quoted values) taken out."""
    return _VARYING.sub("#", text)[:120]


class OneLinePerKind(logging.Filter):
    """For a handler: records with an exception, and records of loggers other than
    mocapd's, become one line each, at most once per kind and interval."""

    def __init__(self, interval_s: float = INTERVAL_S) -> None:
        super().__init__()
        self.limiter = _Limiter(interval_s)

    def filter(self, record: logging.LogRecord) -> bool:
        exc = record.exc_info[1] if record.exc_info else None
        if exc is None and record.name.startswith("mocapd"):
            return True
        text = record.getMessage()
        # the kind: what failed and the exception's type (its message varies with the bytes)
        kind = f"{record.name} {_kind(text)} {type(exc).__name__ if exc else ''}"
        if exc is not None:
            cause = exc.__cause__ or exc.__context__
            text += f": {type(exc).__name__}: {exc}"
            if cause is not None and str(cause) not in str(exc):
                text += f" ({type(cause).__name__}: {cause})"
        held = self.limiter.allow(kind)
        if held is None:
            return False
        text = " ".join(text.split())[:300]
        if held:
            text += f" ({held} more like it in the last minute)"
        record.msg, record.args = text, None
        record.exc_info, record.exc_text, record.stack_info = None, None, None
        return True


class LineLog(io.TextIOBase):
    """A stream (for sys.stdout or sys.stderr) whose lines go to a logger once per kind and
    interval; a printed traceback becomes its last line (the exception)."""

    def __init__(self, logger: logging.Logger, level: int = logging.WARNING,
                 interval_s: float = INTERVAL_S) -> None:
        super().__init__()
        self.log, self.level = logger, level
        self.limiter = _Limiter(interval_s)
        self._partial = ""
        self._lock = threading.Lock()

    def writable(self) -> bool:
        return True

    def isatty(self) -> bool:
        return False

    def write(self, text: str) -> int:
        with self._lock:
            lines = (self._partial + str(text)).split("\n")
            self._partial = lines.pop()[-4096:]
        for line in lines:
            self._line(line)
        return len(text)

    def _line(self, line: str) -> None:
        # a traceback's frames, source lines and joining sentences say nothing a person
        # can act on here: only its last line (the exception) is kept
        if not line.strip() or line[:1].isspace() or line.startswith(
                ("Traceback", "The above exception", "During handling", "Exception in")):
            return
        held = self.limiter.allow(_kind(line))
        if held is not None:
            self.log.log(self.level, "%s%s", " ".join(line.split())[:300],
                         f" ({held} more like it in the last minute)" if held else "")


def install(logger: logging.Logger) -> None:
    """In the view's process: every handler of the root logger filtered, stdout and stderr
    (viser's prints, tracebacks of failing callbacks) turned into rate-limited lines."""
    root = logging.getLogger()
    for handler in root.handlers:
        handler.addFilter(OneLinePerKind())
    sys.stdout = LineLog(logger, logging.WARNING)
    sys.stderr = LineLog(logger, logging.WARNING)


# ---- values from the page ------------------------------------------------------------------

def text(value, what: str, max_len: int = 200) -> str:
    """A text field's value: a string of at most max_len printable characters."""
    if not isinstance(value, str):
        raise UserError(f"{what}: expected text, got {type(value).__name__}")
    if len(value) > max_len or not value.isprintable():
        raise UserError(f"{what}: at most {max_len} printable characters")
    return value


def number(value, what: str, lo: float, hi: float) -> float:
    """A number field's value: finite and within [lo, hi]."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) \
            or not math.isfinite(value) or not lo <= value <= hi:
        raise UserError(f"{what}: expected a number from {lo:g} to {hi:g}, got {value!r}")
    return float(value)


def choice(value, choices, what: str) -> str:
    """A dropdown's value: one of its options (a crafted message can send any string)."""
    if not isinstance(value, str) or value not in choices:
        raise UserError(f"{what}: {str(value)[:40]!r} is not one of the options")
    return value
