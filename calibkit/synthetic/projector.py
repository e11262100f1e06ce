"""A simulated ceiling projector casting dots on the floor and a table, watched by a rig.

The extrinsic calibration (calibkit.calibrate.extrinsic_*) is measured against this. Two ways to see
the dots. The fast 2D path (`observe_dots`) projects every dot's true landing point into
every camera with Gaussian centroid noise: what a perfect detector and decoder would
report, for large scenes and benchmarks. The rendered path (`ProjectorRigSim`) renders the
projector's image with the real EGL renderer (projector.display), lights the floor and the
table top with it through the projector's lens, and gives each camera an 8-bit image of
what it sees, with its own latency, exposure blend and sensor noise, so the whole capture
(settle detection, detection, coded identification) runs as it would on hardware.

Geometry: the projector is an inverse camera (calibkit.synthetic.sim.make_projector); the table is a
box from the floor to `Table.height_m` whose top is lit and whose sides are dark; it hides
what is behind it from a camera and casts a shadow on the floor from the projector.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np

from calibkit.calibrate.extrinsic_capture import CameraDots
from calibkit.core.camera import Camera, Rig
from calibkit.core.geometry import RigArrays, mean_ray_distance
from calibkit.synthetic import sim
from calibkit.synthetic.sim import Table
from projector.display import OffscreenDisplay

SUPERSAMPLE = 3


@dataclass(frozen=True, eq=False)
class ProjectorScene:
    """The truth: a rig, a ceiling projector and the table put in for the second session."""

    rig: Rig
    projector: Camera
    table: Table | None

    def land(self, dots_px: np.ndarray, table_present: bool) -> tuple[np.ndarray, np.ndarray]:
        """Where projector pixels land: world points (N, 3), plane ids (N,) 0 floor, 1 table,
        -1 nowhere."""
        return sim.projector_scene(self.projector, dots_px,
                                   self.table if table_present else None)


def default_table(volume_m: float = 4.0, height_m: float = 0.75) -> Table:
    """A 1.6 x 0.9 m table near the middle of the projector's throw."""
    s = volume_m / 4.0
    return Table(-0.8 * s, 0.8 * s, -0.3 * s, 0.6 * s, height_m)


def make_scene(n_cameras: int = 6, volume_m: float = 4.0, table_height_m: float | None = 0.75,
               size: tuple[int, int] = (640, 480), seed: int = 0) -> ProjectorScene:
    return scene_for_rig(sim.make_rig(n_cameras, volume_m, size, seed=seed), volume_m,
                         table_height_m, seed)


def scene_for_rig(rig: Rig, volume_m: float = 4.0, table_height_m: float | None = 0.75,
                  seed: int = 0) -> ProjectorScene:
    """A given true rig (the simulated hardware) with a ceiling projector and a table."""
    projector = sim.make_projector(volume_m, seed=seed)
    table = None if table_height_m is None else default_table(volume_m, table_height_m)
    return ProjectorScene(rig, projector, table)


def measured_references(scene: ProjectorScene, floor_px: np.ndarray, table_px: np.ndarray,
                        error_m: float = 0.005, height_error_m: float = 0.0, seed: int = 0
                        ) -> dict:
    """What a user with a tape would write down: each reference dot's landing point with
    Gaussian error `error_m` per axis, and the table height with `height_error_m`. Returns
    the fields of extrinsic_reference.References (plain arrays)."""
    rng = np.random.default_rng(seed)
    f_xyz, f_plane = scene.land(floor_px, table_present=False)
    ok = f_plane == 0
    out = {"floor_px": np.asarray(floor_px, float)[ok],
           "floor_xy_m": f_xyz[ok, :2] + rng.normal(0, error_m, (int(ok.sum()), 2))}
    if scene.table is not None and len(table_px):
        t_xyz, t_plane = scene.land(table_px, table_present=True)
        on = t_plane == 1
        out["table_px"] = np.asarray(table_px, float)[on]
        out["table_xy_m"] = t_xyz[on, :2] + rng.normal(0, error_m, (int(on.sum()), 2))
        out["table_height_m"] = scene.table.height_m + rng.normal(0, height_error_m) \
            if height_error_m > 0 else scene.table.height_m
    return out


def table_reference_px(scene: ProjectorScene, inset_m: float = 0.1) -> np.ndarray:
    """Projector pixels that land near the table's corners (inset by `inset_m`): where a
    user would aim reference dots on the table top."""
    t = scene.table
    assert t is not None
    corners = np.array([[t.x0 + inset_m, t.y0 + inset_m, t.height_m],
                        [t.x1 - inset_m, t.y0 + inset_m, t.height_m],
                        [t.x1 - inset_m, t.y1 - inset_m, t.height_m],
                        [t.x0 + inset_m, t.y1 - inset_m, t.height_m],
                        [0.5 * (t.x0 + t.x1), 0.5 * (t.y0 + t.y1), t.height_m]])
    px, _ = scene.projector.project(corners)
    return np.rint(px)


# ---- visibility ------------------------------------------------------------------------------

def _box_hit(origin: np.ndarray, dirs: np.ndarray, table: Table, s_max: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray]:
    """Slab test of rays origin + s dirs (s in (0, s_max)) against the table's box: the entry
    distance (inf when missed) and whether the entry face is the top."""
    lo = np.array([table.x0, table.y0, 0.0])
    hi = np.array([table.x1, table.y1, table.height_m])
    o = np.broadcast_to(origin, dirs.shape)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / dirs
        t1 = (lo - o) * inv
        t2 = (hi - o) * inv
    tmin = np.nanmax(np.minimum(t1, t2), axis=1)
    tmax = np.nanmin(np.maximum(t1, t2), axis=1)
    hit = (tmax >= tmin) & (tmin > 1e-9) & (tmin < s_max)
    entry = np.where(hit, tmin, np.inf)
    top = hit & np.isclose(o[:, 2] + tmin * dirs[:, 2], table.height_m, atol=1e-7)
    return entry, top


def hidden_by_table(centre: np.ndarray, xyz: np.ndarray, table: Table | None) -> np.ndarray:
    """Points (N, 3) that the table's box hides from a viewpoint `centre` (a camera or the
    projector); points on the table top itself are not hidden by it."""
    if table is None or len(xyz) == 0:
        return np.zeros(len(xyz), bool)
    d = xyz - centre
    dist = np.linalg.norm(d, axis=1)
    entry, _ = _box_hit(centre, d / dist[:, None], table, dist - 1e-6)
    return np.isfinite(entry)


def observe_dots(scene: ProjectorScene, dots_px: np.ndarray, table_present: bool,
                 noise_px: float = 0.2, margin_px: float = 4.0, seed: int = 0
                 ) -> list[tuple[np.ndarray, np.ndarray]]:
    """The 2D path: per camera, (indices into dots_px, noisy image positions (N, 2)) of the
    dots it sees: landed, in front, inside the image by `margin_px`, not hidden by the
    table."""
    rng = np.random.default_rng(seed)
    xyz, plane = scene.land(dots_px, table_present)
    landed = np.flatnonzero(plane >= 0)
    table = scene.table if table_present else None
    out = []
    for cam in scene.rig:
        uv, front = cam.project(xyz[landed])
        seen = front & cam.in_image(uv, margin_px)
        seen &= ~hidden_by_table(cam.centre, xyz[landed], table)
        idx = landed[seen]
        out.append((idx, uv[seen] + rng.normal(0.0, noise_px, (len(idx), 2))))
    return out


# ---- rendered images -----------------------------------------------------------------------

@dataclass
class ProjectorSimConfig:
    """The simulated hardware: brightness in camera DN, times in seconds."""

    projector_px: tuple[int, int] = (1280, 800)
    fps: float = 30.0
    projector_latency_s: float = 0.05
    camera_latency_s: tuple[float, ...] | None = None  # per camera; None: drawn from seed
    exposure_s: float = 0.012
    ambient_dn: float = 8.0
    white_dn: float = 170.0
    noise_dn: float = 2.0
    blur_px: float = 0.5
    supersample: int = SUPERSAMPLE  # sub-samples per camera pixel and axis
    seed: int = 0


def camera_latencies(cfg: ProjectorSimConfig, n: int) -> np.ndarray:
    """Each camera's delay (s) from light to delivered frame: given, or drawn from 20 to
    150 ms (a machine-vision camera to a webcam with a deep queue)."""
    if cfg.camera_latency_s is None:
        return np.random.default_rng(cfg.seed + 1).uniform(0.02, 0.15, n)
    lat = np.asarray(cfg.camera_latency_s, float)
    if len(lat) != n:
        raise ValueError("one camera latency per camera is needed")
    return lat


def latency_frames(cfg: ProjectorSimConfig, n: int) -> list[int]:
    """Frames from a pattern request to each camera's first fully changed frame."""
    total = cfg.projector_latency_s + camera_latencies(cfg, n) + cfg.exposure_s
    return [int(math.ceil(t * cfg.fps)) for t in total]


@dataclass
class _Shown:
    t_s: float
    key: int


@dataclass
class ProjectorRigSim:
    """Every camera of the rig watching the projector's light. `show` requests a pattern
    (it appears after the projector's latency); `grab` returns one frame per camera, each
    exposed at its own delay behind the shared clock (cameras differ in latency)."""

    scene: ProjectorScene
    config: ProjectorSimConfig = field(default_factory=ProjectorSimConfig)
    table_present: bool = False

    def __post_init__(self) -> None:
        cfg = self.config
        self.display = OffscreenDisplay(cfg.projector_px)
        self.rng = np.random.default_rng(cfg.seed)
        self.latency_s = camera_latencies(cfg, len(self.scene.rig))
        self.t_s = 0.0
        self.frames = 0
        self._keys = 0
        self.history: list[_Shown] = [_Shown(-1e9, 0)]
        self._images: dict[int, np.ndarray] = {0: np.zeros(cfg.projector_px[::-1], np.float32)}
        self._maps: dict[tuple[int, bool], tuple] = {}
        self._rays: dict[int, np.ndarray] = {}
        self._warped: dict[tuple[int, int], np.ndarray] = {}

    def close(self) -> None:
        self.display.close()

    def __enter__(self) -> ProjectorRigSim:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def set_table(self, present: bool) -> None:
        """The user carries the table in (or out): takes a while, the images change."""
        self.table_present = present
        self._warped.clear()
        self.t_s += 5.0

    def show(self, dots) -> None:
        self._keys += 1
        self._images[self._keys] = self.display.render(dots)
        self.history.append(_Shown(self.t_s + self.config.projector_latency_s, self._keys))
        self._forget()

    def _forget(self) -> None:
        """Drop patterns that no camera's exposure can reach any more (the slowest camera
        still sees what was shown its latency ago)."""
        horizon = self.t_s - float(np.max(self.latency_s)) - 2.0 / self.config.fps
        while len(self.history) > 1 and self.history[1].t_s < horizon:
            old = self.history.pop(0)
            self._images.pop(old.key, None)
            for k in [k for k in self._warped if k[1] == old.key]:
                self._warped.pop(k)

    def _map(self, c: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """For camera c's sub-samples: projector pixel coordinates and a lit mask (plus the
        fraction of each camera pixel that sees lit surface), for the current table state."""
        key = (c, self.table_present)
        if key not in self._maps:
            s = self.config.supersample
            if c not in self._rays:
                self._rays[c] = _camera_rays(self.scene.rig[c], s)
            self._maps[key] = _camera_to_projector(self.scene, c, self.table_present, s,
                                                   self._rays[c])
        return self._maps[key]

    def _warp(self, c: int, key: int) -> np.ndarray:
        img = self._warped.get((c, key))
        if img is None:
            mx, my, lit = self._map(c)
            cam = self.scene.rig[c]
            sampled = cv2.remap(self._images[key], mx, my, cv2.INTER_LINEAR,
                                borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
            sampled[~lit] = 0.0
            pix = cv2.resize(sampled, (cam.width, cam.height), interpolation=cv2.INTER_AREA)
            cfg = self.config
            img = cfg.ambient_dn + (cfg.white_dn - cfg.ambient_dn) * pix
            if cfg.blur_px > 0:
                img = cv2.GaussianBlur(img, (0, 0), cfg.blur_px)
            self._warped[(c, key)] = img
        return img

    def grab(self) -> list[np.ndarray]:
        """The next frame of every camera (uint8), exposed latency_s[c] before now."""
        cfg = self.config
        self.t_s += 1.0 / cfg.fps
        self.frames += 1
        self._forget()
        out = []
        for c, cam in enumerate(self.scene.rig):
            start = self.t_s - self.latency_s[c]
            end = start + cfg.exposure_s
            img = np.zeros((cam.height, cam.width), np.float32)
            for i, shown in enumerate(self.history):
                t0 = max(shown.t_s, start)
                t1 = min(self.history[i + 1].t_s if i + 1 < len(self.history) else np.inf, end)
                if t1 > t0:
                    img += self._warp(c, shown.key) * np.float32((t1 - t0) / cfg.exposure_s)
            img += np.float32(cfg.noise_dn) * self.rng.standard_normal(img.shape, np.float32)
            out.append(np.clip(np.rint(img), 0, 255).astype(np.uint8))
        return out


def _camera_rays(cam: Camera, s: int) -> np.ndarray:
    """Normalised undistorted coordinates of every sub-sample (h*s, w*s, 2): the lens is
    inverted on a grid 4 sub-samples apart and interpolated (the ray field is smooth)."""
    # deferred on purpose: loads SciPy's ndimage only where used
    from scipy.ndimage import map_coordinates

    cam0 = cam.replace(rvec=np.zeros(3), t=np.zeros(3))
    w, h = cam.width * s, cam.height * s
    step = 4
    cx = np.arange(-step, w + 2 * step, step)
    cy = np.arange(-step, h + 2 * step, step)
    gx, gy = np.meshgrid(cx, cy)
    to_px = lambda i: (i + 0.5) / s - 0.5  # noqa: E731 - sub-sample index -> pixels
    coarse = cam0.undistort(np.column_stack([to_px(gx.ravel()), to_px(gy.ravel())]))
    coarse = coarse.reshape(len(cy), len(cx), 2)
    fy, fx = np.mgrid[0:h, 0:w].astype(np.float64)
    at = [(fy.ravel() + step) / step, (fx.ravel() + step) / step]
    return np.column_stack([map_coordinates(coarse[:, :, k], at, order=1) for k in range(2)])


def _camera_to_projector(scene: ProjectorScene, c: int, table_present: bool, s: int,
                         n: np.ndarray):
    """Camera c's sub-samples (normalised rays n) -> projector pixels and a lit mask."""
    cam = scene.rig[c]
    d = np.concatenate([n, np.ones((len(n), 1))], axis=1) @ cam.R  # world directions
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    o = cam.centre
    with np.errstate(divide="ignore", invalid="ignore"):
        s_floor = -o[2] / d[:, 2]
    ok = s_floor > 0
    s_floor = np.where(ok, s_floor, 1.0)
    xyz = o + s_floor[:, None] * d
    table = scene.table if table_present else None
    if table is not None:
        entry, top = _box_hit(o, d, table, np.where(ok, s_floor, np.inf))
        on_box = np.isfinite(entry)
        xyz[on_box] = o + entry[on_box, None] * d[on_box]
        ok &= ~on_box | top  # the box's sides are dark
        # the floor (and nothing else) can lie in the table's shadow
        floor_rows = np.flatnonzero(ok & ~on_box)
        shadow = hidden_by_table(scene.projector.centre, xyz[floor_rows], table)
        ok[floor_rows[shadow]] = False
    ppx, front = scene.projector.project(xyz)
    ok &= front
    shape = (cam.height * s, cam.width * s)
    mx = np.where(ok, ppx[:, 0], -10.0).astype(np.float32).reshape(shape)
    my = np.where(ok, ppx[:, 1], -10.0).astype(np.float32).reshape(shape)
    return mx, my, ok.reshape(shape)


def ray_distance_at_height(estimated: Rig, truth: Rig, z_m: float, volume_m: float,
                           steps: int = 9) -> float:
    """Mean ray distance (mm) at height z: a grid of points at z across the volume, seen
    exactly by the true cameras, cast back as rays by the estimated ones; the mean distance
    between every pair of rays of each point, averaged over points seen by >= 2 cameras."""
    half = 0.4 * volume_m
    g = np.linspace(-half, half, steps)
    gx, gy = np.meshgrid(g, g)
    pts = np.column_stack([gx.ravel(), gy.ravel(), np.full(gx.size, z_m)])
    names = [n for n in truth.names if n in set(estimated.names)]
    point, camera, uv = [], [], []
    for k, name in enumerate(names):
        p, front = truth[name].project(pts)
        seen = np.flatnonzero(front & truth[name].in_image(p))
        point.append(seen)
        camera.append(np.full(len(seen), k))
        uv.append(p[seen])
    point_a, cam_a, uv_a = np.concatenate(point), np.concatenate(camera), np.concatenate(uv)
    est = Rig(tuple(estimated[n] for n in names))
    o, d = RigArrays.from_rig(est).rays(cam_a, uv_a)
    dist = mean_ray_distance(point_a, o, d, len(pts))
    return float(np.nanmean(dist) * 1000.0)


def simulated_dots(scene: ProjectorScene, points_px: np.ndarray, table_present: bool,
                   noise_px: float = 0.2, wrong_ids: float = 0.0, seed: int = 0,
                   shown: np.ndarray | None = None) -> list:
    """The 2D path as the capture's output: per camera extrinsic_capture.CameraDots with the true
    ids (indices into points_px), noisy centroids, and a share `wrong_ids` of dots given
    another dot's id (a decoding error, for testing the outlier rejection). shown: the ids
    the schedule shows (default all)."""
    rng = np.random.default_rng(seed + 7)
    shown = np.arange(len(points_px)) if shown is None else np.asarray(shown, np.int64)
    out = []
    for idx, uv in observe_dots(scene, points_px[shown], table_present, noise_px, seed=seed):
        ids = shown[idx]
        if wrong_ids > 0 and len(ids):
            bad = rng.random(len(ids)) < wrong_ids
            ids[bad] = rng.integers(0, len(points_px), int(bad.sum()))
            _, first = np.unique(ids, return_index=True)
            keep = np.zeros(len(ids), bool)
            keep[first] = True
            ids, uv = ids[keep], uv[keep]
        out.append(CameraDots(ids, uv, np.zeros(len(ids))))
    return out
