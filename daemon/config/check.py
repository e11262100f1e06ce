"""Checking a TOML table's keys and values, with errors that name the file and the key.

Shared by mocapd.toml (daemon.config.mocapd) and the capture nodes' files (daemon.nodes): one line
naming the file, the key and the problem, raised as the UserError a command prints."""

from __future__ import annotations

import math
from pathlib import Path

from calibkit.core.errors import UserError


class _Where:
    """Error messages that name the file and the key."""

    def __init__(self, path: Path | None) -> None:
        self.path = path

    def fail(self, key: str, problem: str):
        where = f"{self.path}: " if self.path else ""
        raise UserError(f"{where}{key}: {problem}")


def _check_keys(w: _Where, table: dict, allowed, prefix: str) -> None:
    for key in table:
        if key not in allowed:
            w.fail(f"{prefix}{key}", "unknown key (allowed: " + ", ".join(sorted(allowed)) + ")")


def finite_number(v) -> bool:
    """A TOML number that is one: not a bool, not nan or inf, an integer within 64 bits."""
    if isinstance(v, bool):
        return False
    if isinstance(v, int):
        return abs(v) < 2**63
    return isinstance(v, float) and math.isfinite(v)


def _number(w, table, key, prefix, default, kind=float, lo=None, hi=None):
    if key not in table:
        return default
    v = table[key]
    if isinstance(v, bool) or not isinstance(v, (int, float)) or (kind is int and
                                                                  not isinstance(v, int)):
        w.fail(prefix + key, f"expected {'an integer' if kind is int else 'a number'}, "
                             f"got {v!r}")
    if not finite_number(v):  # nan and inf pass the range checks below (inf is above any lo)
        w.fail(prefix + key, f"expected a number, got {v!r}")
    if (lo is not None and v < lo) or (hi is not None and v > hi):
        rng = f"between {lo} and {hi}" if hi is not None else f"at least {lo}"
        w.fail(prefix + key, f"must be {rng}, got {v}")
    return kind(v)


def _string(w, table, key, prefix, default=None, choices=None):
    if key not in table:
        if default is None:
            w.fail(prefix + key, "missing (required)")
        return default
    v = table[key]
    if not isinstance(v, str) or not v:
        w.fail(prefix + key, f"expected a non-empty string, got {v!r}")
    if choices and v not in choices:
        w.fail(prefix + key, f"must be one of {', '.join(choices)}; got {v!r}")
    return v


def _bool(w, table, key, prefix, default):
    if key not in table:
        return default
    if not isinstance(table[key], bool):
        w.fail(prefix + key, f"expected true or false, got {table[key]!r}")
    return table[key]


def _table(w, data, key) -> dict:
    v = data.get(key, {})
    if not isinstance(v, dict):
        w.fail(key, f"expected a table [{key}], got {v!r}")
    return v


def _list(w, data, key) -> list:
    v = data.get(key, [])
    if isinstance(v, dict):
        v = [v]
    if not isinstance(v, list) or not all(isinstance(t, dict) for t in v):
        w.fail(key, f"expected tables [[{key}]], got {v!r}")
    return v
