"""How good a wand calibration is: figures on solved and held-out frames, checks for
impossible solutions, a grade in plain words with stated thresholds, and PNG plots.

The held-out figures matter: frames left out of the solve (some at random, some whole
regions of the volume) are triangulated with the solved rig, so an over-fitted rig (one
that explains its own frames but not new ones) shows there. What wrong intrinsics leave
is different: the solve bends the poses until the reprojection looks fine and the space
it reconstructs is quietly warped, millimetres off with an excellent-looking pixel RMS.
A warped space cannot keep a rigid wand's length: it comes out long in one part of the
volume and short in another, or short near the image edges and long at the centre. So the
grade also looks at how the length error varies across the volume and with the distance
from the image centre (`systematics`), which no choice of intrinsics can hide.
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np

from calibkit.calibrate.wand import WandObservations, WandSpec, point_index
from calibkit.calibrate.wand_systematics import (  # noqa: F401 (systematics: re-exported)
    MIN_CELL_FRAMES,
    systematics,
)
from calibkit.core.camera import Rig
from calibkit.core.fileio import write_bytes_atomic
from calibkit.core.geometry import RigArrays, triangulate

# Grade thresholds, on the held-out frames (docs/wand.md explains them).
# (name, reprojection RMS px at most, wand length error SD at most as % of the wand's
# length: per-frame length noise scales with the volume and the cameras' resolution)
GRADES = (
    ("excellent", 0.25, 0.15),
    ("good", 0.5, 0.3),
    ("usable", 1.0, 1.0),
)
# Systematic length errors, each at most as % of the wand's length, per grade (docs/wand.md):
# the spread of the mean length error over cells of the volume, the trend from the image
# centre to its edges, and the bias in the held-out regions. On the simulator's 4 m volume
# a rig 1 mm off (grid RMS) shows about 0.03 % on the first two.
SYSTEMATIC_GRADES = (("excellent", 0.02), ("good", 0.05), ("usable", 0.1))
# Intrinsics the solve moved from the file's, in the file's prior sigmas at most, per grade:
# a file whose values the wand moves many of its own sigmas is wrong or over-confident, and
# then the capture alone vouches for the result (docs/wand.md).
INTRINSIC_SIGMA_GRADES = (("excellent", 3.0), ("good", 5.0))
# How well the solve determines the cameras, per grade: the largest camera position
# standard deviation (the marginals, intrinsics' uncertainty included) over its distance
# from the reference camera, ppm at most. On the simulator (4 m volume) the rig's grid
# error was 0.4-1.8 um per ppm (docs/wand.md: 64-69 ppm for rigs 0.09-0.10 mm off, 118-172
# ppm for 0.20-0.31 mm, 1006 ppm for 0.43 mm, 5657 ppm for 6.1 mm): loose limits, for rigs
# the capture leaves loosely determined, not for tenths of a millimetre.
POSITION_PPM_GRADES = (("excellent", 300.0), ("good", 1500.0))
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
    if len(w) == 0:
        return _no_figures(len(rig))
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
    frame_err, frame_centre, frame_radius = _per_frame(rig, w, cam, pidx, pinfo, tri.xyz, spec)
    return {
        **_length_variation(frame_err, spec),
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
        "frame_length_error_mm": frame_err, "frame_centre_m": frame_centre,
        "frame_radius": frame_radius,
    }


def _length_variation(frame_err_mm: np.ndarray, spec: WandSpec) -> dict:
    """The spread of the end-to-end length over frames in % of its mean (SD / mean): the
    figure that needs no scale, so it means the same for a wand of unknown length."""
    if spec.n_markers < 2 or len(frame_err_mm) < 2:
        return {"wand_length_variation_pct": float("nan"), "length_frames": len(frame_err_mm)}
    length_mm = 1000.0 * spec.length_m + frame_err_mm
    return {"wand_length_variation_pct": float(100.0 * np.std(length_mm, ddof=1)
                                               / np.mean(length_mm)),
            "length_frames": int(len(frame_err_mm))}


def _no_figures(n_cams: int) -> dict:
    """evaluate's figures for frames of which no camera of the rig saw anything."""
    nan = float("nan")
    return {"frames": 0, "observations": 0, "reprojection_rms_px": nan,
            "camera_rms_px": np.full(n_cams, nan), "camera_observations": np.zeros(n_cams, int),
            "wand_length_error_mean_mm": nan, "wand_length_error_sd_mm": nan,
            "wand_length_error_rms_mm": nan, "mean_ray_distance_mm": nan, "behind_share": 0.0,
            "residual_px": np.zeros((0, 2)), "residual_camera": np.zeros(0, int),
            "residual_uv": np.zeros((0, 2)), "xyz": np.zeros((0, 3)),
            "frame_length_error_mm": np.zeros(0), "frame_centre_m": np.zeros((0, 3)),
            "frame_radius": np.zeros(0), "wand_length_variation_pct": nan, "length_frames": 0}


def hold_out(frames: np.ndarray, centre_m: np.ndarray, share: float, seed: int = 0
             ) -> tuple[np.ndarray, np.ndarray]:
    """Frames to keep out of the solve: (at random, in whole regions), about `share` of
    `frames` in all, half each way. The regions are cells of a 4 x 4 x 2 grid over the
    quantiles of the wand's centre (`centre_m`, NaN where unknown), drawn at random until
    they hold half the share: a rig that is right only where it was fitted shows there."""
    rng = np.random.default_rng(seed)
    n_held = int(round(share * len(frames))) if share > 0 else 0
    if n_held == 0:
        return frames[:0], frames[:0]
    known = np.isfinite(centre_m).all(axis=1)
    region = np.zeros(len(frames), dtype=bool)
    if known.sum() >= 16 * MIN_CELL_FRAMES:
        c = centre_m[known]
        key = np.zeros(len(c), dtype=np.int64)
        for axis, bins in enumerate((4, 4, 2)):
            edges = np.quantile(c[:, axis], np.arange(1, bins) / bins)
            key = key * bins + np.searchsorted(edges, c[:, axis])
        cell = np.full(len(frames), -1)
        cell[known] = key
        for k in rng.permutation(np.unique(key)):
            if region.sum() >= n_held // 2:
                break
            region |= cell == k
    rest = np.flatnonzero(~region)
    n_random = max(0, min(len(rest), n_held - int(region.sum())))
    random = np.sort(rng.choice(frames[rest], n_random, replace=False))
    return random, frames[region]


def _per_frame(rig: Rig, w: WandObservations, cam: np.ndarray, pidx: np.ndarray,
               pinfo: np.ndarray, xyz: np.ndarray, spec: WandSpec
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per frame with both end markers triangulated: the end-to-end length error (mm), the
    wand's centre (m), and how far from the image centres it was seen (the mean over its
    observations of the distance from the principal point over the half-diagonal)."""
    if spec.n_markers < 2 or not len(pinfo):
        return np.zeros(0), np.zeros((0, 3)), np.zeros(0)
    frames, f_of = np.unique(pinfo[:, 0], return_inverse=True)
    ends = np.full((len(frames), 2, 3), np.nan)
    first, last = pinfo[:, 1] == 0, pinfo[:, 1] == spec.n_markers - 1
    ends[f_of[first], 0] = xyz[first]
    ends[f_of[last], 1] = xyz[last]
    err = (np.linalg.norm(ends[:, 1] - ends[:, 0], axis=1) - spec.length_m) * 1000.0
    arrays = RigArrays.from_rig(rig)
    half = 0.5 * np.hypot([c.width for c in rig], [c.height for c in rig])
    r = np.hypot(w.uv[:, 0] - arrays.cx[cam], w.uv[:, 1] - arrays.cy[cam]) / half[cam]
    fo = f_of[pidx]
    radius = np.bincount(fo, r, len(frames)) / np.maximum(np.bincount(fo, None, len(frames)), 1)
    ok = np.isfinite(err)
    return err[ok], 0.5 * (ends[ok, 0] + ends[ok, 1]), radius[ok]


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


def _capped(value: float, grades, below: str, worst: str, order: list[str]):
    """(the grade `value` allows under `grades` ((grade, limit), best first; `below` past
    the last limit), the better grade it missed) when that is worse than `worst`, else
    None: one cap of the grade."""
    allowed = next((g for g, limit in grades if value <= limit), below)
    if order.index(allowed) <= order.index(worst):
        return None
    return allowed, order[order.index(allowed) - 1]


def grade(held: dict, found: dict, wand_length_m: float, syst: dict | None = None,
          intrinsics: list[dict] | None = None, basis: str = "held-out",
          position_ppm: tuple[str, float] | None = None) -> tuple[str, str]:
    """(grade, the reason in plain words) from the held-out figures (`basis` names the frames
    they come from: "solved" when none were held out), the checks, the systematic length
    errors (`systematics`) and how far the solve moved each camera's intrinsics from the
    file's (`intrinsics`: rows with largest_change_sigmas, as the report's) and how well the
    solve determines the cameras (`position_ppm`: the camera whose position standard
    deviation, over its distance from the reference camera, is the largest, and that share
    in ppm): the worst of the grades each allows. A figure that could not be computed (NaN)
    caps nothing."""
    name, reason = _grade_held(held, found, wand_length_m, basis)
    if name in ("failed", "poor"):
        return name, reason
    order = [g for g, *_ in GRADES] + ["poor"]
    worst, why = name, ""
    for key, what in (("volume", "across the volume"),
                      ("radius", "from the image centre to its edges"),
                      ("region", "in the held-out regions"),
                      ("trend", "with the wand's position in the volume")):
        pct = (syst or {}).get(f"{key}_pct", float("nan"))
        if not np.isfinite(pct):
            continue
        capped = _capped(pct, SYSTEMATIC_GRADES, "poor", worst, order)
        if capped:
            worst, missed = capped
            why = (f"the wand's length varies {what} by {syst[key + '_mm']:.2f} mm "
                   f"({pct:.3f} % of its length, above the {dict(SYSTEMATIC_GRADES)[missed]} "
                   f"% '{missed}' allows): the reconstructed space is warped, most often by "
                   "wrong intrinsics; recalibrate them, or give them with their uncertainty "
                   "(calibkit intrinsic) so that the wand can refine them")
    moved = [r for r in intrinsics or [] if np.isfinite(r.get("largest_change_sigmas", np.nan))]
    if moved:
        far = max(moved, key=lambda r: r["largest_change_sigmas"])
        sig = far["largest_change_sigmas"]
        capped = _capped(sig, INTRINSIC_SIGMA_GRADES, "usable", worst, order)
        if capped:
            worst, missed = capped
            why = (f"the wand moved camera {far['name']}'s {far['largest_change_parameter']} "
                   f"{sig:.1f} prior sigmas from the intrinsics file (more than the "
                   f"{dict(INTRINSIC_SIGMA_GRADES)[missed]:g} '{missed}' allows): the file's "
                   "intrinsics or their uncertainties are wrong, and what the wand made of "
                   "them is judged by this capture alone; recalibrate the intrinsics "
                   "(calibkit intrinsic) or solve with the monitor's views")
    if position_ppm is not None and np.isfinite(position_ppm[1]):
        cam, ppm = position_ppm
        capped = _capped(ppm, POSITION_PPM_GRADES, "usable", worst, order)
        if capped:
            worst, missed = capped
            why = (f"the capture determines camera {cam}'s position only to {ppm:.0f} ppm of "
                   f"its distance from the reference camera (the solve's own standard "
                   f"deviation; '{missed}' allows {dict(POSITION_PPM_GRADES)[missed]:g} ppm):"
                   " wave the wand through more of the volume and every camera's image, or "
                   "give the intrinsics with their monitor views")
    if why:
        return worst, why
    return name, reason + (f"; systematic length errors within the {dict(SYSTEMATIC_GRADES)[name]}"
                           f" % '{name}' allows")


def _grade_held(held: dict, found: dict, wand_length_m: float,
                basis: str = "held-out") -> tuple[str, str]:
    if not found["ok"]:
        what = [k for k in ("camera_behind_volume", "upside_down", "mirrored") if found[k]]
        return "failed", ("the solution is impossible (" + ", ".join(what).replace("_", " ")
                          + "): recapture or check the floor frame")
    rms, sd = held["reprojection_rms_px"], held["wand_length_error_sd_mm"]
    if not np.isfinite(rms):
        return "poor", (f"no {basis} frame could be triangulated: nothing to grade the rig "
                        "on; recapture with the wand seen by two cameras or more")
    if not wand_length_m > 0 or not np.isfinite(sd):  # a 1-marker wand: pixels only
        for name, max_px, _ in GRADES:
            if rms <= max_px:
                return name, (f"{basis} reprojection {rms:.3f} px <= {max_px} px (no wand "
                              "length to judge)")
        return "poor", f"{basis} reprojection {rms:.3f} px > {GRADES[-1][1]} px"
    pct = 100.0 * sd / (1000.0 * wand_length_m)
    for name, max_px, max_pct in GRADES:
        if rms <= max_px and pct <= max_pct:
            return name, (f"{basis} reprojection {rms:.3f} px <= {max_px} px and wand length "
                          f"spread {sd:.2f} mm = {pct:.2f} % <= {max_pct} % of its length")
    return "poor", (f"{basis} reprojection {rms:.3f} px or wand length spread {sd:.2f} mm "
                    f"({pct:.2f} %) is beyond 'usable' ({GRADES[-1][1]} px, {GRADES[-1][2]} "
                    "%): recapture with more coverage or check the intrinsics")


# ---- plots ------------------------------------------------------------------------------------

def plot_layout(rig: Rig, xyz: np.ndarray, path: Path) -> None:
    """Cameras and wand points from above and from the side (PNG)."""
    # deferred on purpose: loads matplotlib only where used
    import matplotlib

    matplotlib.use("Agg")
    # deferred on purpose: loads matplotlib only where used
    import matplotlib.pyplot as plt


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
    # deferred on purpose: loads matplotlib only where used
    import matplotlib

    matplotlib.use("Agg")
    # deferred on purpose: loads matplotlib only where used
    import matplotlib.pyplot as plt


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


def coverage_png(rig: Rig, camera: np.ndarray, uv: np.ndarray, cells: int = 24) -> bytes:
    """Per camera: where in its image the wand was seen (observations per cell of a
    `cells`-wide grid; blank cells are where it never went), as PNG bytes."""
    # deferred on purpose: loads matplotlib only where used
    import matplotlib

    matplotlib.use("Agg")
    # deferred on purpose: loads matplotlib only where used
    import matplotlib.pyplot as plt

    n = len(rig)
    cols = min(4, n)
    rows = (n + cols - 1) // cols
    fig, axes = plt.subplots(rows, cols, figsize=(4 * cols, 3.2 * rows), squeeze=False)
    for k, ax in enumerate(axes.ravel()):
        if k >= n:
            ax.axis("off")
            continue
        w, h = rig[k].size
        ny = max(1, round(cells * h / w))
        m = camera == k
        hist, _, _ = np.histogram2d(uv[m, 1], uv[m, 0], bins=(ny, cells),
                                    range=((0, h), (0, w)))
        shown = np.where(hist > 0, hist, np.nan)
        ax.imshow(shown, extent=(0, w, h, 0), cmap="viridis", interpolation="nearest")
        filled = 100.0 * np.count_nonzero(hist) / hist.size
        ax.set_title(f"{rig[k].name}: {filled:.0f} % of {cells}x{ny} cells, "
                     f"{int(m.sum())} obs", fontsize=9)
        ax.set_xlim(0, w)
        ax.set_ylim(h, 0)
        ax.set_aspect("equal")
    fig.suptitle("wand coverage per camera")
    data = _png(fig)
    plt.close(fig)
    return data


def _png(fig) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90, bbox_inches="tight")
    return buf.getvalue()
