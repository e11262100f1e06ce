"""A calibration that is off by a chosen amount: the true rig perturbed until it leaves a
given reprojection residual, and that residual measured with the true blob labels.

Why: a real rig is never calibrated exactly, and how far off it is decides how wide the
correspondence and tracking gates must be. Blobs are rendered with the true rig; the
estimating code is handed the perturbed one, as it would be handed a calibration.
"""

from __future__ import annotations

import numpy as np

from calibkit.core.camera import Rig, rotation_from_rvec
from calibkit.core.geometry import RigArrays, triangulate
from calibkit.core.observations import Observations, Truth
from calibkit.synthetic import sim


def perturb(rig: Rig, scale: float, seed: int = 0) -> Rig:
    """Every camera off by `scale` times: 1 mrad of rotation, 2 mm of position, 0.1 % of
    focal length, 0.5 px of principal point and 0.002 of k1 (standard deviations): what a
    calibration of webcams at about 1 px typically gets wrong, in proportion."""
    rng = np.random.default_rng(seed)
    cams = []
    for c in rig:
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        R = rotation_from_rvec(axis * 1e-3 * scale * rng.normal()) @ c.R
        centre = c.centre + rng.normal(0.0, 2e-3 * scale, 3)
        f = 1.0 + rng.normal(0.0, 1e-3 * scale)
        dist = c.dist.copy()
        dist[0] += rng.normal(0.0, 2e-3 * scale)
        cams.append(c.replace(fx=c.fx * f, fy=c.fy * f, cx=c.cx + rng.normal(0.0, 0.5 * scale),
                              cy=c.cy + rng.normal(0.0, 0.5 * scale), dist=dist, R=R,
                              t=-R @ centre))
    return Rig(tuple(cams), dict(rig.quality), dict(rig.meta))


def off_intrinsics(rig: Rig, focal_rel: float, centre_px: float, k1: float,
                   rng: np.random.Generator) -> Rig:
    """The rig's intrinsics as an intrinsic calibration might leave them: every focal length
    off by focal_rel (either sign), the principal point by centre_px (any direction), k1 by
    k1 (either sign); fixed sizes, random signs and directions. Poses are kept."""
    cams = []
    for c in rig:
        sf, sk = rng.choice([-1, 1], 2)
        a = rng.uniform(0, 2 * np.pi)
        cams.append(c.replace(fx=c.fx * (1 + sf * focal_rel), fy=c.fy * (1 + sf * focal_rel),
                              cx=c.cx + centre_px * np.cos(a), cy=c.cy + centre_px * np.sin(a),
                              dist=c.dist + [sk * k1, 0, 0, 0, 0]))
    return Rig(tuple(cams), dict(rig.quality), dict(rig.meta))


def labelled_residual_px(rig: Rig, obs: Observations, min_cameras: int = 3) -> float:
    """The residual as the calibrations define it, measured with the true labels: each
    marker seen by >= min_cameras cameras triangulated from its blobs with `rig`, then the
    RMS over those blobs of their distance (px) to the point's reprojection."""
    real = np.flatnonzero(obs.marker >= 0)
    key = obs.frame[real] * (1 << 20) + obs.marker[real]
    _, point, counts = np.unique(key, return_inverse=True, return_counts=True)
    keep = counts[point] >= min_cameras
    rows = real[keep]
    _, point = np.unique(point[keep], return_inverse=True)
    index = {name: i for i, name in enumerate(rig.names)}
    cam = np.array([index[n] for n in obs.camera_names], dtype=np.int64)[obs.camera[rows]]
    tri = triangulate(rig, point, cam, obs.uv[rows])
    proj, _ = RigArrays.from_rig(rig).project(cam, tri.xyz[point])
    err = np.linalg.norm(proj - obs.uv[rows], axis=1)
    return float(np.sqrt(np.nanmean(err**2)))


def calibration_scene(rig: Rig, noise_px: float, seed: int = 0, n_frames: int = 30,
                      n_markers: int = 30) -> Observations:
    """Blobs of markers spread through the volume, no strays, no occlusion: the kind of
    data a calibration measures its residual on (a wand waved everywhere)."""
    rng = np.random.default_rng(seed)
    lo, hi = sim.volume_box(float(rig.meta.get("volume_m", 4.0)))
    xyz = rng.uniform(lo + 0.1 * (hi - lo), hi - 0.1 * (hi - lo), (n_frames, n_markers, 3))
    truth = Truth(np.repeat(np.arange(n_frames), n_markers),
                  np.tile(np.arange(n_markers), n_frames), xyz.reshape(-1, 3))
    return sim.observe(rig, truth, noise_px=noise_px, seed=seed + 1)


def miscalibrated(rig: Rig, residual_px: float, noise_px: float, seed: int = 0,
                  ) -> tuple[Rig, float]:
    """The true rig perturbed so that, with `noise_px` of centroid noise, its residual on a
    calibration scene is about `residual_px`: (the perturbed rig, the residual measured).

    The residual grows as sqrt(noise part^2 + (a scale)^2); two secant steps on that law
    land within a few per cent. A target below what the noise alone leaves gets the true
    rig (scale 0)."""
    obs = calibration_scene(rig, noise_px, seed + 100)

    def measured(scale: float) -> tuple[Rig, float]:
        out = perturb(rig, scale, seed) if scale > 0 else rig
        return out, labelled_residual_px(out, obs)

    base_rig, r0 = measured(0.0)
    if residual_px <= r0:
        return base_rig, r0
    scale = 1.0
    for _ in range(3):
        _, r = measured(scale)
        gain = np.sqrt(max(r * r - r0 * r0, 1e-12)) / scale
        scale = float(np.sqrt(residual_px**2 - r0**2) / gain)
    return measured(scale)
