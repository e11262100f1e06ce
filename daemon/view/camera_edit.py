"""A camera's detection settings (threshold, blob sizes, mask) changed from the live view.

The change goes into the camera's [[camera]] table in the configuration file (that one
table's lines, the rest of the file kept byte for byte: daemon.view.tomledit), and the
daemon is asked to reload, which hands the new settings to the camera's capture thread
between two frames. A mask made from the page is a PNG beside the configuration, the
format `calibkit mask` writes, so either tool can make or replace it.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import tomllib

from calibkit.core.errors import UserError
from calibkit.vision.masks import load_mask, save_mask
from daemon.view import tomledit

MASK_MARGIN_PX = 4  # masked beyond each blob's own radius: its flickering edge too


def _need_config(config) -> Path:
    if config is None:
        raise UserError("the daemon runs without a configuration file; start it with "
                        "--config PATH to change detection settings from the view")
    return Path(config)


def parse_threshold(text: str) -> float | str:
    """What a user types: "auto" or a pixel value above 0 (below 65536)."""
    t = str(text).strip().lower()
    if t == "auto":
        return "auto"
    try:
        v = float(t)
    except ValueError:
        raise UserError(f'threshold: type "auto" or a pixel value, not {text!r}') from None
    if not 0 < v < 65536:
        raise UserError(f"threshold: a pixel value is above 0 and below 65536, got {text}")
    return int(v) if v.is_integer() else v


def _edit(path: Path, camera: str, change) -> None:
    """Apply change(lines) -> lines to the camera's table and write it, checked."""
    text = path.read_text(encoding="utf-8")
    segs = tomledit.segments(text)
    k = tomledit.find_table(segs, "camera", camera, "[[camera]] table")
    head, lines = segs[k]
    segs[k] = (head, change(list(lines)))
    new_text = tomledit.join(segs)

    def want(old: dict) -> dict:
        tables = [dict(t) for t in old.get("camera", [])]
        for t in tables:
            if t.get("name") == camera:
                t.clear()
                t.update(tomllib.loads("".join(segs[k][1][1:])))
        return {**old, "camera": tables}

    tomledit.write_checked(path, text, new_text, want)


def set_detection(config, camera: str, threshold=None, min_area: float | None = None,
                  max_area: float | None = None) -> None:
    """The camera's threshold and blob size range, each left as it is when None."""
    path = _need_config(config)
    changes = {k: v for k, v in (("threshold", threshold), ("min_area", min_area),
                                 ("max_area", max_area)) if v is not None}
    if "min_area" in changes and "max_area" in changes and \
            changes["min_area"] >= changes["max_area"]:
        raise UserError(f"min area ({min_area}) must be below max area ({max_area})")

    def change(lines):
        for key, value in changes.items():
            lines = tomledit.set_key(lines, key, tomledit.toml_value(value))
        return lines

    _edit(path, camera, change)


def mask_from_blobs(size: tuple[int, int], uv: np.ndarray, area: np.ndarray,
                    margin_px: float = MASK_MARGIN_PX) -> np.ndarray:
    """bool (h, w): a disc over each blob (its area's radius plus margin_px), True where
    detection is to ignore pixels: what the camera sees with no markers in view is a lamp,
    a reflection or another camera's LEDs, never a marker."""
    w, h = size
    mask = np.zeros((h, w), np.uint8)
    r = np.sqrt(np.maximum(np.asarray(area, np.float64), 1.0) / np.pi) + margin_px
    for (x, y), rad in zip(np.round(np.asarray(uv) * 16).astype(np.int64).tolist(),
                           np.round(r * 16).astype(np.int64).tolist(), strict=True):
        cv2.circle(mask, (x, y), rad, 1, -1, shift=4)
    return mask.astype(bool)


def mask_path(config: Path, camera: str) -> Path:
    safe = "".join(ch if ch.isalnum() or ch in "-_" else "_" for ch in camera)
    return config.with_name(f"{config.stem}.{safe}.mask.png")


def set_mask(config, camera: str, mask: np.ndarray | None, merge: bool = True) -> Path | None:
    """Write the camera's mask PNG beside the configuration (added to the one its table
    names when merge) and point the table at it; None clears the table's mask (the PNG is
    kept, for undo by hand). The path written, or None."""
    path = _need_config(config)
    if mask is None:
        _edit(path, camera, lambda lines: tomledit.remove_key(lines, "mask"))
        return None
    # deferred on purpose: loads numba (compiled kernels) only where used
    from daemon.config.mocapd import load_config

    table = next((c for c in load_config(path).cameras if c.name == camera), None)
    if table is None:
        raise UserError(f"no [[camera]] table called {camera!r} in the configuration")
    if merge and table.mask is not None:
        old = load_mask(table.mask)
        if old.shape == mask.shape:
            mask = mask | old
    out = mask_path(path, camera)
    save_mask(out, mask)
    _edit(path, camera, lambda lines: tomledit.set_key(lines, "mask",
                                                       tomledit.toml_value(out.name)))
    return out
