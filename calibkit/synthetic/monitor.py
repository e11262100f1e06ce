"""A simulated camera watching a simulated monitor that shows the rendered dot patterns.

The monitor's image is the real renderer's output (projector.display through headless
EGL), so the simulated calibration measures the same anti-aliased dots a real monitor
shows. Each camera pixel looks along its ray through the true lens model (distortion
included) to the monitor plane; the screen image is sampled there on a 3 x 3 sub-grid per
camera pixel (area integration, so there is no pixel locking), then blurred by the lens and
given sensor noise. Time is simulated too: the display shows a requested pattern only after
its latency, a camera frame exposed across the switch records a blend, frames can be
dropped, and between views the user tilts the monitor (calibkit.synthetic.sim.monitor_views).

`projected_dots` is the fast path for rigs of many cameras: no image, the capture's output
directly. Each dot's outline is projected through the true lens and the centre of the
imaged shape (not the projection of the dot's centre: a tilted disc images off-centre, as
on the real screen) is reported with Gaussian noise, as a perfect decoder would report it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from calibkit.calibrate.dotcapture import DotView
from calibkit.core.camera import Camera
from calibkit.synthetic.sim import MonitorView, monitor_points, monitor_views
from projector.display import OffscreenDisplay
from projector.dots import Dots

SUPERSAMPLE = 3


@dataclass
class MonitorSimConfig:
    """The simulated hardware. Brightness in camera DN (8-bit)."""

    screen_px: tuple[int, int] = (1920, 1080)
    pixel_pitch_mm: float = 0.2715
    fps: float = 30.0
    latency_s: float = 0.07  # request -> light on the glass (input lag + refresh)
    exposure_s: float = 0.012
    black_dn: float = 10.0
    white_dn: float = 200.0
    noise_dn: float = 2.0
    blur_px: float = 0.6
    drop_rate: float = 0.0  # chance that a camera frame is lost
    shake_px: float = 0.0  # the camera shakes: each frame shifted by N(0, shake_px) px
    seed: int = 0


@dataclass
class _Shown:
    """A picture on the glass from t_s on: dots this simulator renders itself, or a frame
    a display already drew (`show_image`)."""

    t_s: float
    dots: Dots | None
    key: int
    image: np.ndarray | None = None


@dataclass
class MonitorSim:
    """One camera, one monitor, a sequence of views. `show` requests a pattern, `grab`
    returns the next camera frame (uint8) as the camera would deliver it."""

    camera: Camera
    views: list[MonitorView]
    config: MonitorSimConfig = field(default_factory=MonitorSimConfig)

    def __post_init__(self) -> None:
        self._display: OffscreenDisplay | None = None
        self.rng = np.random.default_rng(self.config.seed)
        self.t_s = 0.0
        self.view_index = 0
        sw, sh = self.config.screen_px
        self.history: list[_Shown] = [_Shown(-1e9, None, -1, np.zeros((sh, sw), np.float32))]
        self._maps: tuple[np.ndarray, ...] | None = None
        self._ray_cache: np.ndarray | None = None
        self._warped: dict[int, np.ndarray] = {}
        self._keys = 0
        self.frames_grabbed = 0

    @property
    def display(self) -> OffscreenDisplay:
        """The renderer for `show(dots)`, made on first use: a simulator fed frames that a
        display drew (`show_image`) needs no context of its own."""
        if self._display is None:
            self._display = OffscreenDisplay(self.config.screen_px)
        return self._display

    def close(self) -> None:
        if self._display is not None:
            self._display.close()
            self._display = None

    def __enter__(self) -> MonitorSim:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # ---- the user and the display -------------------------------------------------------
    def set_view(self, index: int) -> None:
        """The user tilts the monitor into view `index` (takes a moment: time passes)."""
        self.view_index = index
        self._maps = None
        self._warped.clear()
        self.t_s += 1.0

    def show(self, dots: Dots) -> None:
        """Request a pattern now; it appears after the display latency."""
        self._keys += 1
        self.history.append(_Shown(self.t_s + self.config.latency_s, dots, self._keys))
        self.history = self.history[-4:]

    def show_image(self, screen_image: np.ndarray) -> None:
        """A frame a display drew (float 0..1, the screen's size) is requested now; it is on
        the glass after the latency. This is how the monitor of `calibkit intrinsic
        --display --sim` gets its picture: from the display code itself
        (projector.display.OffscreenDisplay.watch)."""
        sw, sh = self.config.screen_px
        if screen_image.shape != (sh, sw):
            raise ValueError(f"a {screen_image.shape[1]}x{screen_image.shape[0]} frame on a "
                             f"{sw}x{sh} monitor")
        self._keys += 1
        self.history.append(_Shown(self.t_s + self.config.latency_s, None, self._keys,
                                   screen_image))
        self.history = self.history[-4:]

    # ---- the camera -------------------------------------------------------------------------
    def _rays(self) -> np.ndarray:
        """Normalised, undistorted coordinates of every camera sub-sample (n, 2).

        The lens inversion runs on a grid 4 sub-samples apart and is interpolated
        bilinearly in between: the ray field is smooth, the interpolation error stays
        below 0.001 px for webcam lenses, and it is 15 times cheaper than inverting at
        every sub-sample.
        """
        # deferred on purpose: loads SciPy's ndimage only where used
        from scipy.ndimage import map_coordinates

        cam, s = self.camera, SUPERSAMPLE
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
        return np.column_stack([map_coordinates(coarse[:, :, k], at, order=1)
                                for k in range(2)])

    def _screen_maps(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """For each camera sub-sample: screen pixel coordinates (x, y) and a validity mask;
        and the fraction of each camera pixel that sees the screen."""
        if self._maps is None:
            cam, s = self.camera, SUPERSAMPLE
            w, h = cam.width, cam.height
            if self._ray_cache is None:
                self._ray_cache = self._rays()
            ray = self._ray_cache
            view = self.views[self.view_index]
            n = view.R[:, 2]
            # plain elementwise products: numpy's threaded BLAS is slow on a busy machine
            with np.errstate(divide="ignore", invalid="ignore"):
                depth = float(np.dot(n, view.t)) / (ray[:, 0] * n[0] + ray[:, 1] * n[1] + n[2])
            rel = [ray[:, 0] * depth - view.t[0], ray[:, 1] * depth - view.t[1],
                   depth - view.t[2]]
            pitch_m = self.config.pixel_pitch_mm / 1000.0
            # R^T (X - t): screen coordinates in metres, then pixels
            scr = np.column_stack([
                (rel[0] * view.R[0, k] + rel[1] * view.R[1, k] + rel[2] * view.R[2, k]) / pitch_m
                for k in (0, 1)])
            sw, sh = self.config.screen_px
            ok = ((depth > 0) & (scr[:, 0] >= -0.5) & (scr[:, 0] <= sw - 0.5)
                  & (scr[:, 1] >= -0.5) & (scr[:, 1] <= sh - 0.5))
            shape = (h * s, w * s)
            ok = ok.reshape(shape)
            area = cv2.resize(ok.astype(np.float32), (w, h), interpolation=cv2.INTER_AREA)
            self._maps = (scr[:, 0].astype(np.float32).reshape(shape),
                          scr[:, 1].astype(np.float32).reshape(shape), ok, area)
        return self._maps

    def warp(self, screen_image: np.ndarray) -> np.ndarray:
        """The screen image (float 0..1) as the camera's noise-free float image in DN."""
        mx, my, ok, screen_area = self._screen_maps()
        sampled = cv2.remap(screen_image.astype(np.float32), mx, my, cv2.INTER_LINEAR,
                            borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
        sampled[~ok] = 0.0
        h, w = self.camera.height, self.camera.width
        pix = cv2.resize(sampled, (w, h), interpolation=cv2.INTER_AREA)
        cfg = self.config
        # the room is dark (half the black level), the black screen glows a little
        img = cfg.black_dn * (0.5 + 0.5 * screen_area) + (cfg.white_dn - cfg.black_dn) * pix
        if cfg.blur_px > 0:
            img = cv2.GaussianBlur(img, (0, 0), cfg.blur_px)
        return img

    def _warped_for(self, shown: _Shown) -> np.ndarray:
        img = self._warped.get(shown.key)
        if img is None:
            screen = shown.image if shown.image is not None else self.display.render(shown.dots)
            img = self.warp(screen)
            if len(self._warped) > 6:
                self._warped.pop(next(iter(self._warped)))
            self._warped[shown.key] = img
        return img

    def grab(self) -> np.ndarray:
        """The next delivered camera frame (dropped frames are skipped, as a driver would)."""
        cfg = self.config
        while True:
            start = self.t_s
            self.t_s += 1.0 / cfg.fps
            self.frames_grabbed += 1
            if cfg.drop_rate <= 0 or self.rng.random() >= cfg.drop_rate:
                break
        end = start + cfg.exposure_s
        # what the display showed during the exposure, weighted by time
        img = np.zeros((self.camera.height, self.camera.width), np.float32)
        for i, shown in enumerate(self.history):
            t0 = max(shown.t_s, start)
            t1 = min(self.history[i + 1].t_s if i + 1 < len(self.history) else np.inf, end)
            if t1 > t0:
                img += self._warped_for(shown) * np.float32((t1 - t0) / cfg.exposure_s)
        if cfg.shake_px > 0:
            dx, dy = self.rng.normal(0.0, cfg.shake_px, 2)
            img = cv2.warpAffine(img, np.float32([[1, 0, dx], [0, 1, dy]]),
                                 (img.shape[1], img.shape[0]), flags=cv2.INTER_LINEAR,
                                 borderMode=cv2.BORDER_REPLICATE)
        img += np.float32(cfg.noise_dn) * self.rng.standard_normal(img.shape, np.float32)
        return np.clip(np.rint(img), 0, 255).astype(np.uint8)

    # ---- truth ------------------------------------------------------------------------------
    def truth_uv(self, screen_xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Where screen points project in the current view: pixels (N, 2), in-front mask."""
        pts = monitor_points(self.views[self.view_index], screen_xy, self.config.pixel_pitch_mm)
        return self.camera.replace(rvec=np.zeros(3), t=np.zeros(3)).project(pts)


def default_sim_camera(size: tuple[int, int] = (640, 480), seed: int = 0) -> Camera:
    """A webcam-like camera to calibrate: ~60 degree field of view, mild barrel distortion,
    principal point off centre."""
    rng = np.random.default_rng(seed)
    w, h = size
    f = 0.87 * w * rng.uniform(0.95, 1.05)
    return Camera("simcam", size, f, f * rng.uniform(0.998, 1.002),
                  (w - 1) / 2 + rng.uniform(-8, 8), (h - 1) / 2 + rng.uniform(-6, 6), 0.0,
                  (-0.12, 0.08, 0.0006, -0.0004, 0.0))


def make_monitor_sim(n_views: int, size: tuple[int, int] = (640, 480), seed: int = 0,
                     config: MonitorSimConfig | None = None,
                     camera: Camera | None = None, fill: float = 0.8) -> MonitorSim:
    """A camera and the user's tilted views of the monitor. `fill`: how much of the image
    the screen spans; above 1 the screen overflows the image (its edges out of view) and
    the dots reach the image corners."""
    cfg = config or MonitorSimConfig(seed=seed)
    cam = camera or default_sim_camera(size, seed)
    views = monitor_views(cam, n_views, cfg.screen_px, cfg.pixel_pitch_mm, fill=fill,
                          seed=seed)
    return MonitorSim(cam, views, cfg)


def _polygon_centroid(xy: np.ndarray) -> np.ndarray:
    """Area centroids of polygons (N, K, 2) -> (N, 2)."""
    x, y = xy[..., 0], xy[..., 1]
    xn, yn = np.roll(x, -1, axis=1), np.roll(y, -1, axis=1)
    cross = x * yn - xn * y
    area = cross.sum(axis=1) / 2.0
    cx = ((x + xn) * cross).sum(axis=1) / (6.0 * area)
    cy = ((y + yn) * cross).sum(axis=1) / (6.0 * area)
    return np.column_stack([cx, cy])


def projected_dots(camera: Camera, view: MonitorView, screen_xy: np.ndarray,
                   radius_screen_px: float, pixel_pitch_mm: float, noise_px: float,
                   rng: np.random.Generator, margin_px: float = 4.0,
                   outline: int = 32) -> DotView:
    """The dots (screen pixel centres (N, 2), all of one radius) of one monitor view as an
    ideal capture reports them: ids of the dots whose whole image lies `margin_px` inside
    the image, and the centre of each dot's image (the area centroid of its projected
    outline, distortion included) plus Gaussian noise `noise_px` per axis."""
    cam0 = camera.replace(rvec=np.zeros(3), t=np.zeros(3))
    a = np.linspace(0.0, 2.0 * np.pi, outline, endpoint=False)
    ring = radius_screen_px * np.column_stack([np.cos(a), np.sin(a)])
    pts = (np.asarray(screen_xy, np.float64)[:, None, :] + ring[None]).reshape(-1, 2)
    uv, front = cam0.project(monitor_points(view, pts, pixel_pitch_mm))
    uv, front = uv.reshape(-1, outline, 2), front.reshape(-1, outline)
    w, h = camera.size
    inside = ((uv[..., 0] >= margin_px) & (uv[..., 0] <= w - 1 - margin_px)
              & (uv[..., 1] >= margin_px) & (uv[..., 1] <= h - 1 - margin_px))
    seen = np.flatnonzero((front & inside).all(axis=1))
    centre = _polygon_centroid(uv[seen]) + rng.normal(0.0, noise_px, (len(seen), 2))
    radius = float(np.median(np.linalg.norm(uv[seen] - uv[seen].mean(axis=1, keepdims=True),
                                            axis=2))) if len(seen) else float("nan")
    return DotView(seen.astype(np.int64), centre, np.full(len(seen), noise_px), 1,
                   dot_radius_px=radius)
