"""Option parsing shared by several commands."""

from __future__ import annotations

from pathlib import Path

from calibkit.camera import Rig
from calibkit.errors import UserError


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


def truth_rig_path(out: Path) -> Path:
    """Where a simulated run writes the true rig beside its result: NAME.truth.toml."""
    return out.with_name(out.stem + ".truth.toml")
