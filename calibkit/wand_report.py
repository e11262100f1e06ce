"""How good a wand calibration is: figures on solved and held-out frames, checks for
impossible solutions, a grade in plain words with stated thresholds, and PNG plots.

The held-out figures matter most: frames left out of the solve are triangulated with the
solved rig, so an over-fitted rig (one that explains its own frames but not new ones)
shows there and nowhere else.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from calibkit.camera import Rig
from calibkit.geometry import RigArrays, triangulate
from calibkit.wand import WandObservations, WandSpec, point_index

# Grade thresholds, on the held-out frames (docs/wand.md explains them).
# (name, reprojection RMS px at most, wand length error SD at most as % of the wand's
# length: per-frame length noise scales with the volume and the cameras' resolution)
GRADES = (
    ("excellent", 0.25, 0.15),
    ("good", 0.5, 0.3),
    ("usable", 1.0, 1.0),
)
BEHIND_SHARE = 0.01  # more observations than this behind their camera: a mirrored solution


def evaluate(rig: Rig, wand: WandObservations, spec: WandSpec, frames: np.ndarray | None = None,
             camera_of: np.ndarray | None = None) -> dict:
    """Triangulate the wand in `frames` (all when None) with `rig` and measure it.

    camera_of maps the wand's camera numbers to the rig's (-1: not in the rig).
    """
    sel = np.ones(len(wand), dtype=bool) if frames is None else np.isin(wand.frame, frames)
    cam = wand.camera.astype(np.int64) if camera_of is None else camera_of[wand.camera]
    sel &= cam >= 0
    w = wand.select(sel)
    cam = cam[sel]
    pidx, pinfo = point_index(w, spec.n_markers)
    tri = triangulate(rig, pidx, cam, w.uv, n_points=len(pinfo))
    proj, z = RigArrays.from_rig(rig).project(cam, tri.xyz[pidx])
    r = w.uv - proj
    ok = np.isfinite(r[:, 0])
    sq = np.sum(r**2, axis=1)
    n = len(rig)
    count = np.bincount(cam[ok], minlength=n)
    with np.errstate(invalid="ignore", divide="ignore"):
        cam_rms = np.sqrt(np.bincount(cam[ok], weights=sq[ok], minlength=n) / count)
    lengths = _all_lengths(tri.xyz, pinfo, spec)
    err_mm = (lengths[:, 0] - lengths[:, 1]) * 1000.0
    err_mm = err_mm[np.isfinite(err_mm)]
    # triangulation leaves a point out (NaN) when it lands behind one of its cameras: among
    # markers seen twice or more, those are the observations a mirror image puts behind
    seen2 = tri.n_cameras[pidx] >= 2
    behind = np.sum(seen2 & ~ok)
    return {
        "frames": int(len(np.unique(w.frame))),
        "observations": int(ok.sum()),
        "reprojection_rms_px": float(np.sqrt(np.mean(sq[ok]))) if ok.any() else float("nan"),
        "camera_rms_px": cam_rms,
        "camera_observations": count,
        "wand_length_error_mean_mm": float(np.mean(err_mm)) if len(err_mm) else float("nan"),
        "wand_length_error_sd_mm": float(np.std(err_mm)) if len(err_mm) else float("nan"),
        "wand_length_error_rms_mm": float(np.sqrt(np.mean(err_mm**2))) if len(err_mm)
        else float("nan"),
        "mean_ray_distance_mm": float(np.nanmean(tri.ray_dist_m) * 1000.0)
        if np.isfinite(tri.ray_dist_m).any() else float("nan"),
        "behind_share": float(behind / max(1, seen2.sum())),
        "residual_px": r, "residual_camera": cam, "residual_uv": w.uv,
        "xyz": tri.xyz[np.isfinite(tri.xyz[:, 0])],
    }


def _all_lengths(xyz: np.ndarray, pinfo: np.ndarray, spec: WandSpec) -> np.ndarray:
    """(measured, true) distance of every marker pair of every frame, metres."""
    pairs, true = spec.edges()
    key = pinfo[:, 0] * spec.n_markers + pinfo[:, 1]
    out = []
    for (a, b), d in zip(pairs.tolist(), true.tolist(), strict=True):
        ia = np.flatnonzero(pinfo[:, 1] == a)
        want = pinfo[ia, 0] * spec.n_markers + b
        pos = np.minimum(np.searchsorted(key, want), len(key) - 1)
        found = key[pos] == want
        m = np.linalg.norm(xyz[ia[found]] - xyz[pos[found]], axis=1)
        out.append(np.stack([m, np.full(len(m), d)], axis=1))
    return np.concatenate(out) if out else np.zeros((0, 2))


def checks(rig: Rig, points_xyz: np.ndarray, behind_share: float) -> dict:
    """Impossible solutions, each True when found, with what was seen.

    camera_behind_volume: the middle of the wand's points lies behind a camera.
    upside_down: the wand moved mostly below the floor (z < 0), or most cameras sit below it.
    mirrored: more than 1 % of the observations of markers seen twice or more triangulate
    behind a camera (evaluate's behind_share: the "twisted pair" of a two-view start, a
    mirror image of the true rig), or a left-handed camera.
    """
    pts = points_xyz[np.isfinite(points_xyz).all(axis=1)]
    middle = np.median(pts, axis=0) if len(pts) else np.zeros(3)
    depth = np.array([cam.to_camera(middle[None])[0, 2] for cam in rig])
    behind = [cam.name for cam, d in zip(rig, depth, strict=True) if not d > 0]
    below = float(np.median(pts[:, 2])) < 0 if len(pts) else False
    cams_below = float(np.mean(rig.centres()[:, 2] < 0)) > 0.5
    left_handed = [cam.name for cam in rig if np.linalg.det(cam.R) < 0]
    mirrored = behind_share > BEHIND_SHARE or bool(left_handed)
    return {
        "camera_behind_volume": bool(behind), "cameras_behind": behind,
        "upside_down": bool(below or cams_below),
        "median_point_height_m": float(np.median(pts[:, 2])) if len(pts) else float("nan"),
        "mirrored": bool(mirrored), "behind_share": behind_share,
        "ok": not (behind or below or cams_below or mirrored),
    }


def grade(held: dict, found: dict, wand_length_m: float) -> tuple[str, str]:
    """(grade, the reason in plain words) from the held-out figures and the checks."""
    if not found["ok"]:
        what = [k for k in ("camera_behind_volume", "upside_down", "mirrored") if found[k]]
        return "failed", ("the solution is impossible (" + ", ".join(what).replace("_", " ")
                          + "): recapture or check the floor frame")
    rms, sd = held["reprojection_rms_px"], held["wand_length_error_sd_mm"]
    if not wand_length_m > 0 or not np.isfinite(sd):  # a 1-marker wand: pixels only
        for name, max_px, _ in GRADES:
            if rms <= max_px:
                return name, f"held-out reprojection {rms:.3f} px <= {max_px} px (no wand length)"
        return "poor", f"held-out reprojection {rms:.3f} px > {GRADES[-1][1]} px"
    pct = 100.0 * sd / (1000.0 * wand_length_m)
    for name, max_px, max_pct in GRADES:
        if rms <= max_px and pct <= max_pct:
            return name, (f"held-out reprojection {rms:.3f} px <= {max_px} px and wand length "
                          f"spread {sd:.2f} mm = {pct:.2f} % <= {max_pct} % of its length")
    return "poor", (f"held-out reprojection {rms:.3f} px or wand length spread {sd:.2f} mm "
                    f"({pct:.2f} %) is beyond 'usable' ({GRADES[-1][1]} px, {GRADES[-1][2]} "
                    "%): recapture with more coverage or check the intrinsics")


# ---- plots ------------------------------------------------------------------------------------

def plot_layout(rig: Rig, xyz: np.ndarray, path: Path) -> None:
    """Cameras and wand points from above and from the side (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from calibkit.fileio import write_bytes_atomic

    c = rig.centres()
    axes_z = np.array([cam.R[2] for cam in rig])  # optical axes in the world
    pts = xyz[:: max(1, len(xyz) // 3000)]
    fig, (top, side) = plt.subplots(1, 2, figsize=(11, 5))
    for ax, (i, j), title in ((top, (0, 1), "from above (x, y)"),
                              (side, (0, 2), "from the side (x, z)")):
        ax.scatter(pts[:, i], pts[:, j], s=1, c="0.6", label="wand markers")
        ax.scatter(c[:, i], c[:, j], s=30, c="tab:red", label="cameras")
        ax.quiver(c[:, i], c[:, j], axes_z[:, i], axes_z[:, j], color="tab:red", width=0.004)
        for cam, p in zip(rig, c, strict=True):
            ax.annotate(cam.name, (p[i], p[j]), fontsize=8)
        ax.set_aspect("equal")
        ax.set_title(title)
        ax.set_xlabel("xyz"[i] + " (m)")
        ax.set_ylabel("xyz"[j] + " (m)")
    top.legend(loc="upper right", fontsize=8)
    write_bytes_atomic(path, _png(fig))
    plt.close(fig)


def plot_residuals(rig: Rig, figures: dict, path: Path) -> None:
    """Per camera: residual vectors over the image (scaled up), coloured by size (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from calibkit.fileio import write_bytes_atomic

    n = len(rig)
    cols = min(4, n)
    rows = (n + cols - 1) // cols
    fig, axes = plt.subplots(rows, cols, figsize=(4 * cols, 3.2 * rows), squeeze=False)
    r, cam, uv = figures["residual_px"], figures["residual_camera"], figures["residual_uv"]
    scale = 20.0 / max(1e-9, float(np.nanpercentile(np.linalg.norm(r, axis=1), 95)))
    for k, ax in enumerate(axes.ravel()):
        if k >= n:
            ax.axis("off")
            continue
        m = (cam == k) & np.isfinite(r[:, 0])
        m = np.flatnonzero(m)[:: max(1, int(m.sum()) // 2000)]
        size = np.linalg.norm(r[m], axis=1)
        ax.quiver(uv[m, 0], uv[m, 1], r[m, 0] * scale, -r[m, 1] * scale, size, angles="xy",
                  scale_units="xy", scale=1, width=0.003, cmap="viridis")
        ax.set_xlim(0, rig[k].width)
        ax.set_ylim(rig[k].height, 0)
        ax.set_title(f"{rig[k].name}: RMS {figures['camera_rms_px'][k]:.3f} px", fontsize=9)
        ax.set_aspect("equal")
    fig.suptitle(f"residuals x{scale:.0f}")
    write_bytes_atomic(path, _png(fig))
    plt.close(fig)


def _png(fig) -> bytes:
    import io

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90, bbox_inches="tight")
    return buf.getvalue()
