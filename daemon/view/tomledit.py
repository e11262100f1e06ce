"""Editing one table of the configuration file in place, every other line kept as it was.

The view changes a body's name or a camera's threshold in the user's own file, with its
comments and layout. TOML libraries that write files lose both, so the edits work on the
text: the file is cut at its table headers, one table's lines are changed, and the result
is written only if it parses to the old configuration changed exactly as intended (and
passes the daemon's own checks); otherwise nothing is written and the user is told to edit
the file by hand.
"""

from __future__ import annotations

import json
import re
from collections.abc import Callable
from pathlib import Path

import tomllib

from calibkit.core.errors import UserError
from calibkit.core.fileio import write_text_atomic

HEADER = re.compile(r"^\[\[?\s*[A-Za-z0-9_.\-\" ]+\s*\]\]?\s*(#.*)?$")
Segments = list[tuple[str, list[str]]]


def segments(text: str) -> Segments:
    """The file's lines cut at table headers: (header or "" for the top, lines)."""
    out: Segments = [("", [])]
    for line in text.splitlines(keepends=True):
        if HEADER.match(line.rstrip("\r\n")):
            out.append((line.strip(), [line]))
        else:
            out[-1][1].append(line)
    return out


def join(segs: Segments) -> str:
    return "".join("".join(lines) for _, lines in segs)


def find_table(segs: Segments, array: str, name: str, what: str) -> int:
    """Index of the [[array]] table whose name is `name`; UserError naming `what`."""
    for k, (head, lines) in enumerate(segs):
        if head.replace(" ", "").startswith(f"[[{array}]]"):
            try:
                table = tomllib.loads("".join(lines[1:]))
            except tomllib.TOMLDecodeError:
                continue
            if table.get("name") == name:
                return k
    raise UserError(f"no {what} called {name!r} in the configuration")


def _key_line(key: str) -> re.Pattern:
    return re.compile(rf"^(\s*{re.escape(key)}\s*=\s*)([^#\r\n]*?)(\s*(#.*)?)(\r?\n?)$")


def set_key(lines: list[str], key: str, value: str) -> list[str]:
    """The table's lines with `key = value` (value already TOML): its line changed in place
    (a comment after it kept), or added after the table's last key."""
    pattern = _key_line(key)
    for i, line in enumerate(lines):
        m = pattern.match(line)
        if m and i > 0:
            return lines[:i] + [f"{m.group(1)}{value}{m.group(3)}{m.group(5) or chr(10)}"] \
                + lines[i + 1:]
    last = max((i for i, ln in enumerate(lines) if ln.strip() and not ln.lstrip()
                .startswith("#")), default=0)
    end = "\n" if lines[last].endswith("\n") else ""
    head = lines[:last + 1]
    if not end:
        head[-1] = head[-1] + "\n"
    return head + [f"{key} = {value}\n"] + lines[last + 1:]


def remove_key(lines: list[str], key: str) -> list[str]:
    pattern = _key_line(key)
    return [ln for i, ln in enumerate(lines) if i == 0 or not pattern.match(ln)]


def toml_value(value) -> str:
    """A number or a string as TOML writes it (strings as basic strings, JSON-escaped)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int) or (isinstance(value, float) and value.is_integer()):
        return str(int(value))
    if isinstance(value, float):
        return repr(value)
    return json.dumps(str(value))


def write_checked(path: Path, old_text: str, new_text: str,
                  expect: Callable[[dict], dict]) -> None:
    """Write new_text only if it parses to expect(the old file's tables) and the daemon
    accepts it: nothing else may have moved."""
    # deferred on purpose: loads numba (compiled kernels) only where used
    from daemon.config.mocapd import parse_config

    old = tomllib.loads(old_text)
    try:
        new = tomllib.loads(new_text)
    except tomllib.TOMLDecodeError:
        new = None
    if new != expect(old):
        raise UserError(f"{path}: could not edit the table in place; edit the file by hand")
    parse_config(new, path, path.parent)
    write_text_atomic(path, new_text)
