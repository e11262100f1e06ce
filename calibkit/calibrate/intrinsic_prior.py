"""Priors on each camera's intrinsics for the bundle adjustment, and the check that the
intrinsics it refined stayed sane.

Why priors at all: a wand determines focal lengths, principal points and distortion well
where it reached, but not where it did not (an image corner it never visited, a camera
that saw it rarely); the intrinsic step's own result fills that in. Why not its standard
deviations as they are: they count the step's noise only, not what it cannot see (a
monitor that is not flat, a board printed 0.1 % large, the lens's fit beyond the views'
reach), which in practice leaves focal lengths 0.1-0.5 % and principal points 0.5-2 px
off; so each sigma is the reported one inflated, and never below FLOOR. A rig file without
standard deviations (one imported from elsewhere) gets DEFAULT, a loose prior that only
keeps the solve well-posed.

Order of the parameters: GTSAM's Cal3DS2, fx fy skew cx cy k1 k2 p1 p2. Skew is held (no
real camera has any) and k3 is not in Cal3DS2: it stays as the intrinsic step left it.
"""

from __future__ import annotations

import numpy as np

from calibkit.core.camera import Camera, Rig

CAL3DS2 = ("fx", "fy", "skew", "cx", "cy", "k1", "k2", "p1", "p2")
INFLATE = 3.0  # reported standard deviations are multiplied by this (diagonal, unmodelled)
# The least a prior sigma may be: what intrinsic calibrations really leave (relative for the
# focal lengths, pixels for the principal point, unitless for distortion).
FLOOR = {"focal_rel": 0.001, "centre_px": 0.5, "radial": 0.005, "tangential": 0.0005}
# For a rig file without standard deviations, and the most any prior may be: loose enough
# for any honest calibration, tight enough to keep k1/k2 from wandering where the wand
# never went.
DEFAULT = {"focal_rel": 0.01, "centre_px": 5.0, "radial": 0.02, "tangential": 0.002}
SKEW_SIGMA = 1e-6
MAX_PRIOR_SIGMAS = 5.0  # a refined parameter further than this from its prior: a warning


def _sigmas(cam: Camera, table: dict) -> np.ndarray:
    f = 0.5 * (cam.fx + cam.fy)
    return np.array([table["focal_rel"] * f, table["focal_rel"] * f, SKEW_SIGMA,
                     table["centre_px"], table["centre_px"], table["radial"],
                     table["radial"], table["tangential"], table["tangential"]])


def default_sigmas(cam: Camera) -> np.ndarray:
    """The loose prior (DEFAULT) in Cal3DS2 order: for a camera whose intrinsic step's
    views are themselves in the graph, where a prior need only keep the solve well-posed."""
    return _sigmas(cam, DEFAULT)


def reported_std(rig: Rig, name: str) -> dict | None:
    """The intrinsic step's standard deviations for a camera (rig.toml's
    quality.intrinsic.<camera>.std, IntrinsicResult.std's keys), or None."""
    entry = rig.quality.get("intrinsic", {}).get(name, {}) if isinstance(
        rig.quality.get("intrinsic"), dict) else {}
    std = entry.get("std") if isinstance(entry, dict) else None
    if not isinstance(std, dict):
        return None
    try:
        values = {k: float(std[k]) for k in ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2")}
    except (KeyError, TypeError, ValueError):
        return None
    return values if all(np.isfinite(v) and v >= 0 for v in values.values()) else None


def prior_sigmas(rig: Rig, names: list[str] | None = None) -> tuple[np.ndarray, list[str]]:
    """(n, 9) prior sigmas in Cal3DS2 order for the cameras `names` (all when None), and
    the source of each row: 'intrinsic step' or 'default'."""
    rows, source = [], []
    for name in names or rig.names:
        cam = rig[name]
        floor, cap = _sigmas(cam, FLOOR), _sigmas(cam, DEFAULT)
        std = reported_std(rig, name)
        if std is None:
            rows.append(cap)
            source.append("default")
            continue
        given = np.array([std["fx"], std["fy"], 0.0, std["cx"], std["cy"], std["k1"],
                          std["k2"], std["p1"], std["p2"]])
        sigma = np.clip(INFLATE * given, floor, cap)
        sigma[2] = SKEW_SIGMA
        rows.append(sigma)
        source.append("intrinsic step")
    return np.array(rows).reshape(-1, 9), source


def cal3ds2_vector(cam: Camera) -> np.ndarray:
    return np.array([cam.fx, cam.fy, cam.skew, cam.cx, cam.cy, *cam.dist[:4]])


def _corner_radius(cam: Camera) -> float:
    """The largest undistorted radius (normalised) of the image's corners."""
    w, h = cam.size
    corners = np.array([[-0.5, -0.5], [w - 0.5, -0.5], [-0.5, h - 0.5], [w - 0.5, h - 0.5]])
    return float(np.max(np.linalg.norm(cam.undistort(corners), axis=1)))


def folds_over(cam: Camera, r_max: float) -> bool:
    """True when the radial distortion r (1 + k1 r^2 + k2 r^4 + k3 r^6) stops growing before
    r_max: the lens model then maps two radii to one pixel, a sign that k1, k2 (and k3)
    were not determined out there."""
    k1, k2, _p1, _p2, k3 = cam.dist
    r = np.linspace(0.0, r_max, 200)
    r2 = r * r
    slope = 1.0 + 3.0 * k1 * r2 + 5.0 * k2 * r2**2 + 7.0 * k3 * r2**3
    return bool(np.any(slope <= 0.0))


def image_shift_px(before: Camera, after: Camera, steps: int = 9) -> float:
    """The most a pixel of the image moves between two intrinsics of one camera: the same
    ray seen through each (over a grid spanning the image)."""
    w, h = before.size
    gx, gy = np.meshgrid(np.linspace(0, w - 1, steps), np.linspace(0, h - 1, steps))
    pix = np.column_stack([gx.ravel(), gy.ravel()])
    moved = after.normalised_to_pixels(before.undistort(pix))
    return float(np.max(np.linalg.norm(moved - pix, axis=1)))


def check_refined(start: Rig, refined: Rig, sigmas: np.ndarray) -> tuple[list[dict], list[str]]:
    """Per camera, how far the refined intrinsics moved (focal %, principal point px, the
    largest pixel shift over the image, the largest change in prior sigmas) and warnings:
    a parameter more than MAX_PRIOR_SIGMAS from its prior (the intrinsics file and the wand
    disagree), or a lens model that folds over inside the image."""
    rows, warnings = [], []
    for k, (a, b) in enumerate(zip(start, refined, strict=True)):
        moved = (cal3ds2_vector(b) - cal3ds2_vector(a)) / sigmas[k]
        worst = int(np.argmax(np.abs(moved)))
        row = {"name": a.name, "focal_change_pct": 100.0 * ((b.fx + b.fy) / (a.fx + a.fy) - 1),
               "centre_change_px": float(np.hypot(b.cx - a.cx, b.cy - a.cy)),
               "image_shift_px": image_shift_px(a, b),
               "largest_change_sigmas": float(abs(moved[worst])),
               "largest_change_parameter": CAL3DS2[worst]}
        rows.append(row)
        if abs(moved[worst]) > MAX_PRIOR_SIGMAS:
            warnings.append(f"camera {a.name}: the wand moved {CAL3DS2[worst]} by "
                            f"{abs(moved[worst]):.1f} prior sigmas from the intrinsics file: "
                            "check that the file belongs to this camera and lens")
        if folds_over(b, _corner_radius(b)) and not folds_over(a, _corner_radius(a)):
            warnings.append(f"camera {a.name}: the refined lens model folds over inside the "
                            "image (k1/k2 not determined at its edges): wave the wand into "
                            "the image corners, or keep the intrinsics fixed")
    return rows, warnings
