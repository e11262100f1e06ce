"""The intrinsic step's target views kept for the wand solve: per camera, each view's dots
(their known positions on the target plane, their image pixels) and the view's pose.

Why keep them: the intrinsic step's standard deviations summarise these views only as a
diagonal, and a summary inflated for safety at that; with the views themselves in the wand's
graph (calibkit.calibrate.bundle.TargetData), the intrinsics are refined by the monitor and the wand
together, each weighted by its own noise. The file sits beside the intrinsic step's rig file
(NAME.views.npz) and the rig file names it (quality.intrinsic.<camera>.views_file, relative
to the rig file), so later steps find it from the rig file alone.
"""

from __future__ import annotations

import io
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from calibkit.core.errors import UserError
from calibkit.core.fileio import write_bytes_atomic

KEY = "views_file"  # in quality.intrinsic.<camera>


@dataclass(eq=False)
class PlaneViews:
    """Target observations of several cameras: row k is a dot at xyz (metres, target frame,
    z = 0) seen at uv (pixels, as the intrinsic step used them: perspective bias removed)
    in view `view[k]` of camera `camera[k]`. Views are numbered over all cameras; each has
    its target-to-camera pose (rvec, tvec) from the intrinsic step."""

    camera_names: tuple[str, ...]
    camera: np.ndarray  # (M,) int, index into camera_names
    view: np.ndarray  # (M,) int, index into the view arrays
    xyz: np.ndarray  # (M, 3)
    uv: np.ndarray  # (M, 2)
    view_camera: np.ndarray  # (V,) int
    view_rvec: np.ndarray  # (V, 3)
    view_tvec: np.ndarray  # (V, 3)

    def __len__(self) -> int:
        return len(self.uv)

    def cameras(self, names) -> PlaneViews:
        """The views of the cameras `names` (those present), renumbered to that order."""
        names = tuple(names)
        local = np.array([names.index(n) if n in names else -1 for n in self.camera_names],
                         dtype=np.int64).reshape(-1)
        keep_view = local[self.view_camera] >= 0 if len(self.view_camera) else \
            np.zeros(0, bool)
        new_view = np.cumsum(keep_view) - 1
        rows = keep_view[self.view] if len(self.view) else np.zeros(0, bool)
        return PlaneViews(names, local[self.camera[rows]], new_view[self.view[rows]],
                          self.xyz[rows], self.uv[rows], local[self.view_camera[keep_view]],
                          self.view_rvec[keep_view], self.view_tvec[keep_view])


def from_result(name: str, views, result) -> PlaneViews:
    """One camera's views (calibkit.calibrate.intrinsic.PlaneView list, as the solve used
    them) and its IntrinsicResult: the inlier dots only, with the solved view poses."""
    n = np.array([len(v) for v in views], dtype=np.int64)
    view = np.repeat(np.arange(len(views)), n)
    xyz = np.concatenate([v.obj for v in views]) if len(views) else np.zeros((0, 3))
    uv = np.concatenate([v.uv for v in views]) if len(views) else np.zeros((0, 2))
    keep = np.asarray(result.inliers, dtype=bool)
    return PlaneViews((name,), np.zeros(int(keep.sum()), np.int64), view[keep], xyz[keep],
                      uv[keep], np.zeros(len(views), np.int64),
                      np.asarray(result.rvecs, np.float64).reshape(-1, 3),
                      np.asarray(result.tvecs, np.float64).reshape(-1, 3))


def merge(old: PlaneViews | None, new: PlaneViews) -> PlaneViews:
    """`old` with the cameras of `new` replaced by (or added as) `new`'s."""
    if old is None:
        return new
    rest = tuple(n for n in old.camera_names if n not in new.camera_names)
    a = old.cameras(rest)
    names = rest + new.camera_names
    off_c, off_v = len(rest), len(a.view_camera)
    cat = np.concatenate
    return PlaneViews(names, cat([a.camera, new.camera + off_c]),
                      cat([a.view, new.view + off_v]), cat([a.xyz, new.xyz]),
                      cat([a.uv, new.uv]), cat([a.view_camera, new.view_camera + off_c]),
                      cat([a.view_rvec, new.view_rvec]), cat([a.view_tvec, new.view_tvec]))


def views_path(rig_path: str | Path) -> Path:
    """Where the intrinsic step writing `rig_path` keeps its views: NAME.views.npz."""
    rig_path = Path(rig_path)
    return rig_path.with_name(rig_path.stem + ".views.npz")


def save(path: str | Path, views: PlaneViews) -> None:
    buf = io.BytesIO()
    np.savez_compressed(buf, camera_names=np.array(views.camera_names), camera=views.camera,
                        view=views.view, xyz=views.xyz, uv=views.uv,
                        view_camera=views.view_camera, view_rvec=views.view_rvec,
                        view_tvec=views.view_tvec)
    write_bytes_atomic(path, buf.getvalue())


def load(path: str | Path) -> PlaneViews:
    path = Path(path)
    try:
        z = np.load(path, allow_pickle=False)
        return PlaneViews(tuple(str(n) for n in z["camera_names"]),
                          z["camera"].astype(np.int64), z["view"].astype(np.int64),
                          z["xyz"].reshape(-1, 3), z["uv"].reshape(-1, 2),
                          z["view_camera"].astype(np.int64), z["view_rvec"].reshape(-1, 3),
                          z["view_tvec"].reshape(-1, 3))
    except FileNotFoundError:
        raise UserError(f"{path}: no such file (the intrinsic step's views: rerun calibkit "
                        "intrinsic, or pass --no-monitor-views)") from None
    except (OSError, KeyError, ValueError):
        raise UserError(f"{path}: not a views file written by calibkit intrinsic") from None


def load_existing(path: str | Path) -> PlaneViews | None:
    """The views file at `path`, or None when there is none yet."""
    return load(path) if Path(path).exists() else None


def referenced(quality: dict, rig_path: str | Path) -> list[Path]:
    """The views files a rig file's quality.intrinsic names, resolved against the rig
    file's folder (each once)."""
    per = quality.get("intrinsic") if isinstance(quality, dict) else None
    if not isinstance(per, dict):
        return []
    out: list[Path] = []
    for entry in per.values():
        ref = entry.get(KEY) if isinstance(entry, dict) else None
        if isinstance(ref, str) and ref:
            p = Path(rig_path).parent / ref
            if p not in out:
                out.append(p)
    return out


def load_for(quality: dict, rig_path: str | Path, names) -> PlaneViews | None:
    """Every named camera's views that the rig file at `rig_path` points to, or None when
    it points to none (a rig file from elsewhere: the solve falls back on priors)."""
    found: PlaneViews | None = None
    for p in referenced(quality, rig_path):
        found = merge(found, load(p)) if found is not None else load(p)
    if found is None:
        return None
    sub = found.cameras(names)
    return sub if len(sub) else None


def rebase(quality: dict, old_rig: str | Path, new_rig: str | Path) -> dict:
    """quality.intrinsic with its views_file references made relative to `new_rig`'s
    folder instead of `old_rig`'s: for a step that passes the intrinsics on to a rig file
    written elsewhere."""
    per = quality.get("intrinsic")
    if not isinstance(per, dict):
        return quality
    out = {}
    for name, entry in per.items():
        if isinstance(entry, dict) and isinstance(entry.get(KEY), str):
            target = (Path(old_rig).parent / entry[KEY]).resolve()
            rel = os.path.relpath(target, Path(new_rig).resolve().parent)
            entry = {**entry, KEY: Path(rel).as_posix()}
        out[name] = entry
    return {**quality, "intrinsic": out}
