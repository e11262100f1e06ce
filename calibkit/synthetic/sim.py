"""The simulated rig: cameras, moving markers, and what the cameras see, with ground truth.

Every algorithm is measured against this. A scene is a `Truth` table (marker positions per
frame); `observe` turns it into the 2D observations real cameras would report (noise,
dropouts, stray blobs, unsynchronised clocks, markers whose images overlap merged into one
blob: calibkit.synthetic.blobs) and `render_frame` into 8-bit images. All of it
is deterministic for a seed. The capture volume is a box: x and y in [-V/2, V/2], z in
[0, V/2] for a volume V metres across, with the floor at z = 0.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from calibkit.core.camera import WEBCAM_DIST, Camera, Rig, look_at, rvec_from_rotation
from calibkit.core.errors import UserError
from calibkit.core.observations import Observations, Truth
from calibkit.synthetic.blobs import merge_blobs
from calibkit.synthetic.spots import render_spots

MARKER_RADIUS_M = 0.007  # a 14 mm retro-reflective ball


def volume_box(volume_m: float) -> tuple[np.ndarray, np.ndarray]:
    """(low, high) corners of the capture volume."""
    half = volume_m / 2.0
    return np.array([-half, -half, 0.0]), np.array([half, half, half])


def _check(ok: bool, message: str) -> None:
    if not ok:
        raise UserError(message)


# ---- rigs ----------------------------------------------------------------------------------

def make_rig(n_cameras: int = 6, volume_m: float = 4.0, size: tuple[int, int] = (640, 480),
             fov_deg: float = 70.0, dist: Sequence[float] = WEBCAM_DIST, seed: int = 0) -> Rig:
    """Cameras cam0..camN-1 on a ring around the volume, alternately high and low, each
    looking into it (as cameras are mounted on a room's walls); true intrinsics and poses.

    fov_deg is the horizontal field of view; principal points and aspect ratios vary a
    little per camera, as real cameras do.
    """
    _check(2 <= n_cameras <= 32, f"--cameras must be between 2 and 32, got {n_cameras}")
    _check(0.1 <= volume_m <= 10.0, f"--volume must be between 0.1 and 10 m, got {volume_m}")
    _check(10.0 <= fov_deg <= 150.0, f"--fov must be between 10 and 150 degrees, got {fov_deg}")
    w, h = int(size[0]), int(size[1])
    _check(w >= 16 and h >= 16, f"image size must be at least 16x16 pixels, got {w}x{h}")
    rng = np.random.default_rng(seed)
    f = (w / 2.0) / math.tan(math.radians(fov_deg) / 2.0)
    radius = 0.8 * volume_m
    cams = []
    for i in range(n_cameras):
        azimuth = 2 * math.pi * i / n_cameras + rng.uniform(-0.1, 0.1) + math.pi / 8
        height = (0.6 if i % 2 == 0 else 0.35) * volume_m
        centre = [radius * math.cos(azimuth), radius * math.sin(azimuth), height]
        target = [rng.normal(0, 0.03) * volume_m, rng.normal(0, 0.03) * volume_m,
                  0.18 * volume_m]
        R, t = look_at(centre, target)
        cams.append(Camera(f"cam{i}", (w, h), f, f * (1 + rng.normal(0, 0.002)),
                           (w - 1) / 2 + rng.normal(0, 0.01 * w),
                           (h - 1) / 2 + rng.normal(0, 0.01 * h), 0.0, dist,
                           rvec_from_rotation(R), t))
    return Rig(tuple(cams), meta={"source": "calibkit sim rig", "volume_m": volume_m,
                                  "seed": seed})


# ---- scenes ----------------------------------------------------------------------------------

def _frames_truth(positions: np.ndarray) -> Truth:
    """Truth from positions (F, K, 3); NaN positions are left out."""
    n_frames, k = positions.shape[:2]
    frame = np.repeat(np.arange(n_frames), k)
    marker = np.tile(np.arange(k), n_frames)
    xyz = positions.reshape(-1, 3)
    keep = np.isfinite(xyz).all(axis=1)
    return Truth(frame[keep], marker[keep], xyz[keep])


def static_markers(n_markers: int, n_frames: int = 1, volume_m: float = 4.0,
                   seed: int = 0) -> Truth:
    """Markers standing still, spread through the inner part of the volume."""
    _check(n_markers >= 1, f"--markers must be at least 1, got {n_markers}")
    _check(n_frames >= 1, f"--frames must be at least 1, got {n_frames}")
    lo, hi = volume_box(volume_m)
    margin = 0.1 * (hi - lo)
    rng = np.random.default_rng(seed)
    xyz = rng.uniform(lo + margin, hi - margin, size=(n_markers, 3))
    return _frames_truth(np.broadcast_to(xyz, (n_frames, n_markers, 3)))


def _hand_path(n_frames: int, fps: float, lo: np.ndarray, hi: np.ndarray, speed_m_s: float,
               rng: np.random.Generator) -> np.ndarray:
    """A smooth path like a hand's: waypoints through the box joined by a spline, with
    pauses (a waypoint held) and turns. (F, 3)."""
    from scipy.interpolate import CubicSpline  # scipy is imported when a scene needs it

    duration = n_frames / fps
    times, points = [0.0], [rng.uniform(lo, hi)]
    while times[-1] < duration + 1.0:
        nxt = rng.uniform(lo, hi)
        step = np.linalg.norm(nxt - points[-1]) / (speed_m_s * rng.uniform(0.6, 1.4))
        times.append(times[-1] + max(step, 0.2))
        points.append(nxt)
        if rng.random() < 0.15:  # a pause
            times.append(times[-1] + rng.uniform(0.2, 0.6))
            points.append(nxt + rng.normal(0, 0.002, 3))
    spline = CubicSpline(np.array(times), np.array(points), bc_type="clamped")
    return spline(np.arange(n_frames) / fps)


def wand_motion(n_frames: int, fps: float = 100.0, volume_m: float = 4.0,
                spacing_m: Sequence[float] = (0.0, 0.2, 0.5), seed: int = 0) -> Truth:
    """A wand waved through the volume: marker k sits spacing_m[k] along the rod from marker 0.

    The rod's centre follows a hand-like path and its direction turns smoothly, so every
    camera sees it at many places and angles, as in a real wand dance.
    """
    # deferred on purpose: loads SciPy's interpolation, SciPy's optimisers... only where used
    from scipy.interpolate import CubicSpline

    _check(n_frames >= 1, f"--frames must be at least 1, got {n_frames}")
    _check(fps > 0, f"--fps must be positive, got {fps}")
    spacing = np.asarray(spacing_m, dtype=np.float64)
    _check(spacing.size >= 1 and np.all(np.isfinite(spacing)),
           "--spacing must be one or more distances in metres")
    rng = np.random.default_rng(seed)
    lo, hi = volume_box(volume_m)
    half_len = float(np.ptp(spacing)) / 2
    lo_c = lo + [0.1 * volume_m, 0.1 * volume_m, 0.05 * volume_m + half_len]
    hi_c = hi - [0.1 * volume_m, 0.1 * volume_m, 0.05 * volume_m]
    hi_c = np.maximum(hi_c, lo_c + 1e-3)
    centre = _hand_path(n_frames, fps, lo_c, hi_c, 0.3 * volume_m, rng)
    # direction: a smooth random unit vector, kept away from pointing at the cameras' axis
    key_t = np.arange(0, n_frames / fps + 2.0, 0.8)
    keys = rng.normal(size=(len(key_t), 3))
    keys[:, 2] *= 0.6
    keys /= np.linalg.norm(keys, axis=1, keepdims=True)
    # each key within 90 degrees of the last, so the interpolated direction never passes
    # near zero (where normalising it would spin the wand faster than a hand can)
    for i in range(1, len(keys)):
        if keys[i] @ keys[i - 1] < 0:
            keys[i] = -keys[i]
    direction = CubicSpline(key_t, keys)(np.arange(n_frames) / fps)
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    offsets = spacing - spacing.mean()
    positions = centre[:, None, :] + offsets[None, :, None] * direction[:, None, :]
    return _frames_truth(positions)


@dataclass(frozen=True, eq=False)
class SimBody:
    """A simulated rigid body: its markers in its own frame and its true poses."""

    name: str
    id: int
    markers_body: np.ndarray  # (k, 3) metres, body frame (centroid at the origin)
    poses: np.ndarray  # (F, 4, 4) body-to-world
    marker_ids: np.ndarray  # (k,) ids in the Truth table


def _body_layout(k: int, size_m: float, existing: list[np.ndarray],
                 rng: np.random.Generator) -> np.ndarray:
    """k marker positions with distinct inter-marker distances, unlike any existing body."""
    min_gap = 0.03 * size_m  # distances within a body at least this far apart
    min_diff = 0.1 * size_m  # a body's distance set this far from every other body's
    for _ in range(5000):
        pts = rng.uniform(-size_m, size_m, size=(k, 3))
        pts[:, 2] *= 0.5  # flattish, like markers on a drone or a plate
        pts -= pts.mean(axis=0)
        d = np.sort(np.linalg.norm(pts[:, None] - pts[None], axis=2)[np.triu_indices(k, 1)])
        if d[0] < 0.4 * size_m or np.min(np.diff(d), initial=np.inf) < min_gap:
            continue
        if any(len(o) == len(d) and np.max(np.abs(o - d)) < min_diff for o in existing):
            continue
        existing.append(d)
        return pts
    raise UserError(f"cannot place {k} markers with distinct distances; use fewer bodies")


def rigid_body_motion(n_bodies: int, n_frames: int, fps: float = 100.0, volume_m: float = 4.0,
                      markers_per_body: int | Sequence[int] = 4,
                      seed: int = 0) -> tuple[Truth, list[SimBody]]:
    """Rigid bodies (3 to 8 markers, distinct inter-marker distances) moving smoothly through
    the volume, turning as they go; bodies may cross each other's paths."""
    # deferred on purpose: loads SciPy's sparse graphs, SciPy's spatial only where used
    from scipy.spatial.transform import Rotation, RotationSpline

    _check(n_bodies >= 1, f"--bodies must be at least 1, got {n_bodies}")
    _check(n_frames >= 1, f"--frames must be at least 1, got {n_frames}")
    counts = ([int(markers_per_body)] * n_bodies if np.ndim(markers_per_body) == 0
              else [int(k) for k in markers_per_body])
    _check(len(counts) == n_bodies and all(3 <= k <= 8 for k in counts),
           "rigid bodies need 3 to 8 markers each")
    rng = np.random.default_rng(seed)
    lo, hi = volume_box(volume_m)
    size = min(0.12, 0.04 * volume_m)
    inner_lo = lo + [0.15 * volume_m, 0.15 * volume_m, 0.05 * volume_m + size]
    inner_hi = hi - [0.15 * volume_m, 0.15 * volume_m, 0.05 * volume_m]
    existing: list[np.ndarray] = []
    t = np.arange(n_frames) / fps
    bodies, positions = [], []
    next_id = 0
    for b in range(n_bodies):
        layout = _body_layout(counts[b], size, existing, rng)
        centre = _hand_path(n_frames, fps, inner_lo, inner_hi, 0.2 * volume_m, rng)
        key_t = np.arange(0, t[-1] + 3.0, 1.0)
        key_rot = Rotation.from_rotvec(rng.normal(0, 0.6, size=(len(key_t), 3)))
        rot = RotationSpline(key_t, key_rot)(t)
        poses = np.tile(np.eye(4), (n_frames, 1, 1))
        poses[:, :3, :3] = rot.as_matrix()
        poses[:, :3, 3] = centre
        world = np.einsum("fij,kj->fki", poses[:, :3, :3], layout) + centre[:, None, :]
        ids = np.arange(next_id, next_id + counts[b])
        next_id += counts[b]
        bodies.append(SimBody(f"body{b}", b + 1, layout, poses, ids))
        positions.append(world)
    return _frames_truth(np.concatenate(positions, axis=1)), bodies


# ---- what the cameras report -----------------------------------------------------------------

def _dense(truth: Truth) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Truth as (frames (F,), marker ids (K,), positions (F, K, 3) with NaN where absent)."""
    frames = np.unique(truth.frame)
    markers = np.unique(truth.marker)
    pos = np.full((len(frames), len(markers), 3), np.nan)
    pos[np.searchsorted(frames, truth.frame), np.searchsorted(markers, truth.marker)] = truth.xyz
    return frames, markers, pos


def _shifted(pos: np.ndarray, shift_frames: np.ndarray) -> np.ndarray:
    """Positions at fractional frame offsets (per frame), by linear interpolation in time."""
    n = len(pos)
    if n < 2 or not np.any(shift_frames):
        return pos
    at = np.clip(np.arange(n) + shift_frames, 0, n - 1)
    i0 = np.minimum(np.floor(at).astype(np.int64), n - 2)
    a = (at - i0)[:, None, None]
    return pos[i0] * (1 - a) + pos[i0 + 1] * a


BLOB_MODELS = ("threshold", "multi", "ideal")


def observe(rig: Rig, truth: Truth, noise_px: float = 0.0, dropout: float = 0.0,
            ghosts_per_camera: float = 0.0, fps: float = 100.0,
            clock_offset_ns: Sequence[float] | None = None, jitter_ns: float = 0.0,
            seed: int = 0, marker_radius_m: float = MARKER_RADIUS_M,
            blobs: str = "threshold") -> Observations:
    """The blobs each camera reports for a scene.

    A camera captures frame f at f / fps plus its clock offset plus jitter (unsynchronised
    cameras); markers are taken where they were at that moment (linear interpolation of the
    truth between frames). Only markers in front of a camera and inside its image are seen;
    each is hidden with probability `dropout`; `noise_px` is Gaussian noise on the centres;
    stray blobs (marker -1) appear `ghosts_per_camera` times per frame on average.

    `blobs` says how a camera's detector turns the markers' image discs (radius = marker
    radius * focal / depth) into blobs, as real cameras do (see merge_blobs): "threshold"
    (the default: discs that overlap are one blob), "multi" (a detector that separates
    touching spots while each keeps its own brightest point) or "ideal" (every marker its
    own blob at its exact projection, overlapping or not: for tests that need clean blobs).
    A merged blob's `marker` is the marker that gave it most of its light.
    """
    _check(noise_px >= 0, f"--noise-px must not be negative, got {noise_px}")
    _check(0 <= dropout < 1, f"--dropout must be in [0, 1), got {dropout}")
    _check(ghosts_per_camera >= 0, f"--ghosts must not be negative, got {ghosts_per_camera}")
    _check(fps > 0, f"--fps must be positive, got {fps}")
    _check(blobs in BLOB_MODELS, f"--blobs must be one of {', '.join(BLOB_MODELS)}, got "
                                 f"{blobs!r}")
    rng = np.random.default_rng(seed)
    frames, markers, pos = _dense(truth)
    offsets = np.zeros(len(rig)) if clock_offset_ns is None else np.asarray(
        clock_offset_ns, dtype=np.float64)
    _check(len(offsets) == len(rig), "one clock offset per camera is needed")
    parts = []
    period_ns = 1e9 / fps
    n_merged = 0
    for c, cam in enumerate(rig):
        jitter = rng.normal(0.0, jitter_ns, len(frames)) if jitter_ns > 0 else np.zeros(len(frames))
        t_ns = np.round(frames * period_ns + offsets[c] + jitter).astype(np.int64)
        at = _shifted(pos, (offsets[c] + jitter) / period_ns)
        flat = at.reshape(-1, 3)
        finite = np.isfinite(flat).all(axis=1)
        uv, in_front = cam.project(np.where(finite[:, None], flat, 0.0))
        depth = cam.to_camera(np.where(finite[:, None], flat, 0.0))[:, 2]
        seen = finite & in_front & cam.in_image(uv, margin_px=1.0)
        seen &= rng.random(len(seen)) >= dropout
        idx = np.flatnonzero(seen)
        fi, mi = np.divmod(idx, len(markers))
        radius_px = marker_radius_m * cam.fx / depth[idx]
        peak = np.clip(255.0 * np.minimum(1.0, (2.5 / depth[idx]) ** 2), 40, 255)
        if blobs == "ideal":
            uv_seen, area = uv[idx], np.maximum(np.pi * radius_px**2, 1.0)
        else:
            merged = merge_blobs(fi, uv[idx], radius_px, depth[idx], peak,
                                 separate=blobs == "multi")
            fi, mi = fi[merged.dominant], mi[merged.dominant]
            uv_seen, area, peak = merged.uv, np.maximum(merged.area_px, 1.0), merged.peak
            n_merged += int(np.sum(merged.n_markers > 1))
        if noise_px > 0:
            uv_seen = uv_seen + rng.normal(0.0, noise_px, (len(fi), 2))
        n_ghost = rng.poisson(ghosts_per_camera, len(frames)) if ghosts_per_camera > 0 else \
            np.zeros(len(frames), dtype=np.int64)
        gf = np.repeat(np.arange(len(frames)), n_ghost)
        g_uv = rng.uniform([0, 0], [cam.width - 1, cam.height - 1], size=(len(gf), 2))
        parts.append(Observations(
            rig.names, [c_.size for c_ in rig],
            np.concatenate([frames[fi], frames[gf]]), np.full(len(fi) + len(gf), c),
            np.concatenate([t_ns[fi], t_ns[gf]]), np.concatenate([uv_seen, g_uv]),
            np.concatenate([area, rng.uniform(2, 30, len(gf))]),
            np.concatenate([peak, rng.uniform(40, 255, len(gf))]),
            np.concatenate([markers[mi], np.full(len(gf), -1)]), fps))
    obs = Observations.concatenate(parts).sorted()
    obs.fps = fps
    obs.meta = {"simulated": True, "noise_px": noise_px, "dropout": dropout,
                "ghosts_per_camera": ghosts_per_camera, "seed": seed, "blobs": blobs,
                "merged_blobs": n_merged}
    return obs


def render_frame(camera: Camera, xyz: np.ndarray, marker_radius_m: float = MARKER_RADIUS_M,
                 background: float = 8.0, noise_sigma: float = 2.0, seed=0,
                 peak: float = 230.0, blur_px: float = 0.5,
                 stray: np.ndarray | None = None, xyz_end: np.ndarray | None = None,
                 occluders: np.ndarray | None = None,
                 motion_samples: int = 9) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """An 8-bit image of markers as `camera` sees them: (image, true centres (N, 2), visible).

    A marker's spot shrinks with distance (radius = marker radius * focal / depth) and dims
    with it; `stray` (S, 3) rows of (u, v, radius_px) add static reflections such as lamps
    (S, 4 with each one's own brightness in DN: calibkit.synthetic.reflections).
    Motion blur: with `xyz_end` (the positions when the exposure ends) each spot is smeared
    along its path during the exposure, and its true centre is the path's mean, which is
    what an ideal centroid of the smear measures. Occlusion: a marker whose centre is
    covered by a nearer marker's disc is hidden, and so is one behind any of `occluders`
    ((K, 4) spheres: x, y, z, radius in metres, e.g. a body or an arm).
    """
    xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    n = len(xyz)
    if xyz_end is None:
        path = xyz[None]
    else:
        xyz_end = np.asarray(xyz_end, dtype=np.float64).reshape(n, 3)
        a = (np.arange(motion_samples) + 0.5) / motion_samples
        path = xyz[None] * (1 - a)[:, None, None] + xyz_end[None] * a[:, None, None]
    flat = path.reshape(-1, 3)
    uv_all, front_all = camera.project(flat)
    uv_all = uv_all.reshape(len(path), n, 2)
    in_front = front_all.reshape(len(path), n).all(axis=0)
    uv = uv_all.mean(axis=0)
    depth = camera.to_camera(path.mean(axis=0))[:, 2]
    safe_depth = np.where(in_front, depth, 1.0)
    radius = marker_radius_m * camera.fx / safe_depth
    visible = in_front & camera.in_image(uv)
    visible &= ~_hidden_by_markers(uv, radius, safe_depth, visible)
    if occluders is not None and len(occluders):
        visible &= ~_hidden_by_spheres(camera.centre, path.mean(axis=0),
                                       np.asarray(occluders, dtype=np.float64).reshape(-1, 4))
    brightness = peak * np.clip((3.0 / safe_depth) ** 2, 0.35, 1.0)
    k = len(path)
    draw_uv = uv_all[:, visible].reshape(-1, 2)
    draw_r = np.tile(radius[visible], k)
    draw_peak = np.tile(brightness[visible], k) / k
    if stray is not None and len(stray):
        stray = np.asarray(stray, dtype=np.float64)
        stray = stray.reshape(-1, stray.shape[-1] if stray.ndim == 2 else 3)
        draw_uv = np.concatenate([draw_uv, stray[:, :2]])
        draw_r = np.concatenate([draw_r, stray[:, 2]])
        draw_peak = np.concatenate([draw_peak, stray[:, 3] if stray.shape[1] > 3
                                    else np.full(len(stray), peak)])
    image = render_spots(camera.size, draw_uv, draw_r, draw_peak, background=background,
                         noise_sigma=noise_sigma, blur_px=blur_px, rng=seed)
    return image, uv, visible


def _hidden_by_markers(uv: np.ndarray, radius: np.ndarray, depth: np.ndarray,
                       candidates: np.ndarray) -> np.ndarray:
    """Markers whose image centre lies inside the disc of a nearer marker."""
    idx = np.flatnonzero(candidates)
    hidden = np.zeros(len(uv), dtype=bool)
    if len(idx) < 2:
        return hidden
    d = np.linalg.norm(uv[idx, None] - uv[None, idx], axis=2)
    nearer = depth[idx][None, :] < depth[idx][:, None]
    hidden[idx] = np.any(nearer & (d < radius[idx][None, :]), axis=1)
    return hidden


def _hidden_by_spheres(centre: np.ndarray, xyz: np.ndarray, spheres: np.ndarray) -> np.ndarray:
    """Markers whose line of sight from the camera centre passes through a sphere."""
    ray = xyz - centre  # (N, 3)
    length = np.linalg.norm(ray, axis=1)
    direction = ray / np.maximum(length, 1e-12)[:, None]
    to_sphere = spheres[None, :, :3] - centre  # (1, K, 3)
    along = np.einsum("nk,nmk->nm", direction, np.broadcast_to(to_sphere, (len(xyz),
                                                                           *to_sphere.shape[1:])))
    closest = np.linalg.norm(to_sphere - along[..., None] * direction[:, None, :], axis=2)
    before = (along > 0) & (along < length[:, None])
    return np.any(before & (closest < spheres[None, :, 3]), axis=1)


# ---- a monitor in front of a camera; a projector over the floor ------------------------------

@dataclass(frozen=True, eq=False)
class MonitorView:
    """A monitor's pose in one view: monitor-to-camera (R, t). The monitor frame has its
    origin at the centre of screen pixel (0, 0), x along rows, y down columns, z into the
    screen, in metres."""

    R: np.ndarray
    t: np.ndarray


def monitor_points(view: MonitorView, screen_px: np.ndarray, pixel_pitch_mm: float) -> np.ndarray:
    """Screen pixel coordinates (N, 2) -> points (N, 3) in the camera's frame."""
    px = np.asarray(screen_px, dtype=np.float64).reshape(-1, 2)
    local = np.column_stack([px * pixel_pitch_mm / 1000.0, np.zeros(len(px))])
    return local @ view.R.T + view.t


def monitor_views(camera: Camera, n_views: int, screen_px: tuple[int, int] = (1920, 1080),
                  pixel_pitch_mm: float = 0.2715, fill: float = 0.8, max_tilt_deg: float = 35.0,
                  seed: int = 0) -> list[MonitorView]:
    """Poses a user would hold a monitor in front of a camera: the screen fills about `fill`
    of the image, tilted about both axes (alternating sides, so focal length is determined)
    and slightly rotated in-plane."""
    # deferred on purpose: loads SciPy's sparse graphs, SciPy's spatial only where used
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed)
    width_m = screen_px[0] * pixel_pitch_mm / 1000.0
    height_m = screen_px[1] * pixel_pitch_mm / 1000.0
    distance = max(camera.fx * width_m / (fill * camera.width),
                   camera.fy * height_m / (fill * camera.height))
    views = []
    for i in range(n_views):
        sign = 1 if i % 2 == 0 else -1
        ax = np.radians(sign * rng.uniform(0.3, 1.0) * max_tilt_deg) if i % 3 != 2 else 0.0
        ay = np.radians(-sign * rng.uniform(0.3, 1.0) * max_tilt_deg) if i % 3 != 1 else 0.0
        az = np.radians(rng.uniform(-10, 10))
        R = Rotation.from_euler("xyz", [ax, ay, az]).as_matrix()
        centre_local = np.array([width_m / 2, height_m / 2, 0.0])
        centre_cam = np.array([rng.uniform(-0.05, 0.05) * distance,
                               rng.uniform(-0.05, 0.05) * distance,
                               distance * rng.uniform(0.95, 1.15)])
        views.append(MonitorView(R, centre_cam - R @ centre_local))
    return views


@dataclass(frozen=True)
class Table:
    """A table top: an axis-aligned rectangle at `height_m` (metres, world frame)."""

    x0: float
    x1: float
    y0: float
    y1: float
    height_m: float


def make_projector(volume_m: float = 4.0, size: tuple[int, int] = (1280, 800),
                   fov_deg: float = 60.0, seed: int = 0) -> Camera:
    """A ceiling projector modelled as an inverse camera looking down at the floor."""
    rng = np.random.default_rng(seed)
    f = (size[0] / 2.0) / math.tan(math.radians(fov_deg) / 2.0)
    centre = [rng.normal(0, 0.02) * volume_m, rng.normal(0, 0.02) * volume_m, 0.8 * volume_m]
    R, t = look_at(centre, [0.0, 0.0, 0.0], up=(0.0, 1.0, 0.0))
    return Camera("projector", size, f, f, (size[0] - 1) / 2, (size[1] - 1) / 2 + 0.1 * size[1],
                  0.0, (0.02, 0.0, 0.0, 0.0, 0.0), rvec_from_rotation(R), t)


def projector_scene(projector: Camera, dots_px: np.ndarray,
                    table: Table | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Where projector pixels land: world points (N, 3) and plane ids (N,): 0 floor, 1 table,
    -1 nowhere (a ray that points up). The table top hides the floor beneath it."""
    origins, dirs = projector.rays(np.asarray(dots_px, dtype=np.float64).reshape(-1, 2))
    with np.errstate(divide="ignore", invalid="ignore"):
        s_floor = -origins[:, 2] / dirs[:, 2]
    xyz = origins + s_floor[:, None] * dirs
    plane = np.where(s_floor > 0, 0, -1)
    if table is not None:
        with np.errstate(divide="ignore", invalid="ignore"):
            s_table = (table.height_m - origins[:, 2]) / dirs[:, 2]
        hit = origins + s_table[:, None] * dirs
        on_top = ((s_table > 0) & (hit[:, 0] >= table.x0) & (hit[:, 0] <= table.x1)
                  & (hit[:, 1] >= table.y0) & (hit[:, 1] <= table.y1))
        xyz[on_top] = hit[on_top]
        plane[on_top] = 1
    xyz[plane < 0] = np.nan
    return xyz, plane
