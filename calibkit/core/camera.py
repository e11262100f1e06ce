"""The camera model (pinhole + OpenCV distortion + pose) and the rig, an ordered set of cameras.

Conventions (docs/formats.md): pose is world-to-camera, x_cam = R @ x_world + t, so the
centre is -R^T t; the distortion is OpenCV's (k1, k2, p1, p2, k3) so a camera can be handed
to OpenCV as it is; pixel centres sit at integer coordinates. Every method is vectorised
over points.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from calibkit.core.rigfile import read_rig, save_rig

# Lens profiles measured on real cameras, reused by the simulator and the tests.
# A 658x492 Basler machine-vision camera with a short lens (strong barrel distortion).
BASLER_658x492_DIST = (-0.38, 0.16, 0.0, 0.0, 0.0)
# A typical USB webcam: mild barrel distortion.
WEBCAM_DIST = (-0.05, 0.02, 0.0, 0.0, 0.0)


def rotation_from_rvec(rvec: np.ndarray) -> np.ndarray:
    """Rodrigues' formula, numerically safe near zero rotation."""
    rvec = np.asarray(rvec, dtype=np.float64).reshape(3)
    theta = float(np.linalg.norm(rvec))
    if theta < 1e-12:
        kx, ky, kz = rvec
        return np.eye(3) + np.array([[0.0, -kz, ky], [kz, 0.0, -kx], [-ky, kx, 0.0]])
    k = rvec / theta
    kx, ky, kz = k
    kk = np.array([[0.0, -kz, ky], [kz, 0.0, -kx], [-ky, kx, 0.0]])
    return np.eye(3) + np.sin(theta) * kk + (1.0 - np.cos(theta)) * (kk @ kk)


def rvec_from_rotation(R: np.ndarray) -> np.ndarray:
    """Inverse of rotation_from_rvec; exact for angles up to and including pi."""
    # deferred on purpose: loads SciPy's sparse graphs, SciPy's spatial only where used
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(np.asarray(R, dtype=np.float64)).as_rotvec()


def look_at(centre: Sequence[float], target: Sequence[float],
            up: Sequence[float] = (0.0, 0.0, 1.0)) -> tuple[np.ndarray, np.ndarray]:
    """World-to-camera (R, t) for a camera at `centre` whose optical axis points at `target`.

    The image's y axis points as far down the world's `up` as it can (OpenCV cameras have
    y down), so a camera looking at the floor from a wall sees the floor at the image bottom.
    """
    centre = np.asarray(centre, dtype=np.float64)
    z = np.asarray(target, dtype=np.float64) - centre
    z /= np.linalg.norm(z)
    up = np.asarray(up, dtype=np.float64)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-9:  # looking straight along `up`: any x will do
        x = np.cross(z, np.array([0.0, 1.0, 0.0]))
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    return R, -R @ centre


@dataclass(frozen=True, eq=False)
class Camera:
    """One calibrated camera. Frozen: changing a value means making a new camera."""

    name: str
    size: tuple[int, int]  # (width, height) in pixels
    fx: float
    fy: float
    cx: float
    cy: float
    skew: float = 0.0
    dist: np.ndarray = field(default_factory=lambda: np.zeros(5))  # k1, k2, p1, p2, k3
    rvec: np.ndarray = field(default_factory=lambda: np.zeros(3))  # world-to-camera rotation
    t: np.ndarray = field(default_factory=lambda: np.zeros(3))  # world-to-camera translation

    def __post_init__(self) -> None:
        object.__setattr__(self, "size", (int(self.size[0]), int(self.size[1])))
        for name in ("fx", "fy", "cx", "cy", "skew"):
            object.__setattr__(self, name, float(getattr(self, name)))
        dist = np.zeros(5)
        given = np.asarray(self.dist, dtype=np.float64).ravel()
        dist[: min(5, given.size)] = given[:5]
        object.__setattr__(self, "dist", dist)
        object.__setattr__(self, "rvec", np.asarray(self.rvec, dtype=np.float64).reshape(3).copy())
        object.__setattr__(self, "t", np.asarray(self.t, dtype=np.float64).reshape(3).copy())
        object.__setattr__(self, "_R", rotation_from_rvec(self.rvec))
        for arr in (self.dist, self.rvec, self.t, self._R):
            arr.flags.writeable = False

    # ---- construction -------------------------------------------------------------------
    @classmethod
    def from_matrices(cls, name: str, size: tuple[int, int], K: np.ndarray,
                      dist: Sequence[float] = (0, 0, 0, 0, 0), R: np.ndarray | None = None,
                      t: Sequence[float] = (0, 0, 0)) -> Camera:
        K = np.asarray(K, dtype=np.float64)
        rvec = np.zeros(3) if R is None else rvec_from_rotation(R)
        return cls(name, size, K[0, 0], K[1, 1], K[0, 2], K[1, 2], K[0, 1],
                   np.asarray(dist, dtype=np.float64), rvec, np.asarray(t, dtype=np.float64))

    def replace(self, **changes) -> Camera:
        """A copy with some fields changed; `R=` may be given instead of `rvec=`."""
        if "R" in changes:
            changes["rvec"] = rvec_from_rotation(changes.pop("R"))
        return dataclasses.replace(self, **changes)

    # ---- derived values -----------------------------------------------------------------
    @property
    def R(self) -> np.ndarray:
        return self._R  # type: ignore[attr-defined]

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, self.skew, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def centre(self) -> np.ndarray:
        return -self.R.T @ self.t

    @property
    def width(self) -> int:
        return self.size[0]

    @property
    def height(self) -> int:
        return self.size[1]

    @property
    def projection_matrix(self) -> np.ndarray:
        """3x4 P = K [R | t] of the undistorted (normalised-then-K) camera."""
        return self.K @ np.hstack([self.R, self.t[:, None]])

    # ---- the model ----------------------------------------------------------------------
    def to_camera(self, points: np.ndarray) -> np.ndarray:
        """World points (N, 3) in this camera's frame."""
        return np.asarray(points, dtype=np.float64) @ self.R.T + self.t

    def distort(self, normalised: np.ndarray) -> np.ndarray:
        """Apply OpenCV's lens distortion to normalised coordinates (N, 2)."""
        xy = np.asarray(normalised, dtype=np.float64)
        x, y = xy[..., 0], xy[..., 1]
        k1, k2, p1, p2, k3 = self.dist
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
        yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
        return np.stack([xd, yd], axis=-1)

    def normalised_to_pixels(self, normalised: np.ndarray) -> np.ndarray:
        """Distort and apply K: normalised (N, 2) -> pixels (N, 2)."""
        d = self.distort(normalised)
        u = self.fx * d[..., 0] + self.skew * d[..., 1] + self.cx
        v = self.fy * d[..., 1] + self.cy
        return np.stack([u, v], axis=-1)

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World points (N, 3) -> pixels (N, 2) and a mask of points in front of the camera.

        Points behind the camera still get a (meaningless) pixel so arrays stay aligned;
        callers must use the mask.
        """
        pc = self.to_camera(np.atleast_2d(points))
        z = pc[:, 2]
        in_front = z > 1e-9
        safe_z = np.where(in_front, z, 1.0)
        normalised = pc[:, :2] / safe_z[:, None]
        return self.normalised_to_pixels(normalised), in_front

    def in_image(self, pixels: np.ndarray, margin_px: float = 0.0) -> np.ndarray:
        """Mask of pixels inside the image, `margin_px` away from the border."""
        p = np.atleast_2d(pixels)
        return ((p[:, 0] >= -0.5 + margin_px) & (p[:, 0] <= self.width - 0.5 - margin_px)
                & (p[:, 1] >= -0.5 + margin_px) & (p[:, 1] <= self.height - 0.5 - margin_px))

    def undistort(self, pixels: np.ndarray, iterations: int = 20) -> np.ndarray:
        """Pixels (N, 2) -> normalised, undistorted image coordinates (N, 2).

        Inverts the distortion by Newton's method on the analytic 2x2 Jacobian, started at
        the distorted point: converges in a few steps even for strong barrel lenses, where
        OpenCV's default fixed-point iteration still leaves errors near the corners.
        """
        p = np.atleast_2d(np.asarray(pixels, dtype=np.float64))
        yd = (p[:, 1] - self.cy) / self.fy
        xd = (p[:, 0] - self.cx - self.skew * yd) / self.fx
        target = np.stack([xd, yd], axis=-1)
        k1, k2, p1, p2, k3 = self.dist
        if not np.any(self.dist):
            return target
        xy = target.copy()
        for _ in range(iterations):
            x, y = xy[:, 0], xy[:, 1]
            r2 = x * x + y * y
            radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
            dradial = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)  # d radial / d r2
            fx_ = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x) - target[:, 0]
            fy_ = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y - target[:, 1]
            j11 = radial + 2.0 * x * x * dradial + 2.0 * p1 * y + 6.0 * p2 * x
            j12 = 2.0 * x * y * dradial + 2.0 * p1 * x + 2.0 * p2 * y
            j21 = 2.0 * x * y * dradial + 2.0 * p1 * x + 2.0 * p2 * y
            j22 = radial + 2.0 * y * y * dradial + 6.0 * p1 * y + 2.0 * p2 * x
            det = j11 * j22 - j12 * j21
            det = np.where(np.abs(det) < 1e-12, 1e-12, det)
            dx = (j22 * fx_ - j12 * fy_) / det
            dy = (-j21 * fx_ + j11 * fy_) / det
            xy[:, 0] -= dx
            xy[:, 1] -= dy
            if max(np.max(np.abs(dx), initial=0.0), np.max(np.abs(dy), initial=0.0)) < 1e-15:
                break
        return xy

    def rays(self, pixels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixels (N, 2) -> world ray origins (N, 3) and unit directions (N, 3)."""
        n = self.undistort(pixels)
        d_cam = np.concatenate([n, np.ones((n.shape[0], 1))], axis=1)
        d = d_cam @ self.R  # R^T applied to each row
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        return np.broadcast_to(self.centre, d.shape).copy(), d

    def __repr__(self) -> str:
        c = self.centre
        return (f"Camera({self.name!r}, {self.width}x{self.height}, f=({self.fx:.1f}, "
                f"{self.fy:.1f}), c=({self.cx:.1f}, {self.cy:.1f}), "
                f"centre=({c[0]:.3f}, {c[1]:.3f}, {c[2]:.3f}))")


@dataclass(frozen=True, eq=False)
class Rig:
    """An ordered set of uniquely named cameras, plus the calibration's figures."""

    cameras: tuple[Camera, ...]
    quality: dict = field(default_factory=dict)  # calibration figures, free-form numbers
    meta: dict = field(default_factory=dict)  # date, source command, ...

    def __post_init__(self) -> None:
        object.__setattr__(self, "cameras", tuple(self.cameras))
        names = [c.name for c in self.cameras]
        if len(set(names)) != len(names):
            raise ValueError(f"camera names must be unique, got {names}")

    def __len__(self) -> int:
        return len(self.cameras)

    def __iter__(self) -> Iterator[Camera]:
        return iter(self.cameras)

    def __getitem__(self, key: int | str) -> Camera:
        if isinstance(key, str):
            return self.cameras[self.index(key)]
        return self.cameras[key]

    @property
    def names(self) -> list[str]:
        return [c.name for c in self.cameras]

    def index(self, name: str) -> int:
        for i, cam in enumerate(self.cameras):
            if cam.name == name:
                return i
        raise KeyError(name)

    def replace_camera(self, camera: Camera) -> Rig:
        """A rig with the camera of the same name replaced."""
        i = self.index(camera.name)
        cams = list(self.cameras)
        cams[i] = camera
        return dataclasses.replace(self, cameras=tuple(cams))

    def centres(self) -> np.ndarray:
        return np.array([c.centre for c in self.cameras]).reshape(-1, 3)

    @classmethod
    def load(cls, path: str | Path) -> Rig:
        """A rig from a rig.toml or OpenCV YAML file (calibkit.core.rigfile checks it)."""
        found = read_rig(path)
        return cls(tuple(Camera(**c) for c in found.cameras), quality=found.quality,
                   meta=found.meta)

    def save(self, path: str | Path) -> None:
        save_rig(self, path)
