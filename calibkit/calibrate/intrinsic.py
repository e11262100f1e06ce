"""Intrinsic calibration from points on a flat target: the solve, its uncertainty, coverage,
guidance between views, perspective-bias correction and the distortion plot.

The target is a monitor showing dots (calibkit.calibrate.dotcapture) or a printed board
(calibkit.calibrate.board); either way a view is (points on the plane z = 0 in metres,
image pixels).
The solve starts from OpenCV's calibrateCamera and refines every parameter and view pose
with a robust (soft-L1) least-squares fit, so a few misidentified or disturbed points
cannot pull it; the parameter standard deviations come from the covariance at the optimum.

Why the bias correction: the image of a disc's centre is not the centre of the disc's
image when the disc is tilted (the far half looks smaller). For a disc of radius rho the
error grows with rho^2; with the poses of a first solve it is computed exactly (the disc
is a conic, the homography maps it to the image conic, whose centre is what the centroid
measures), subtracted, and the solve repeated.
"""

from __future__ import annotations

import io
from dataclasses import dataclass, field

import cv2
import numpy as np

from calibkit.core.camera import Camera, rotation_from_rvec
from calibkit.core.errors import UserError

PARAMS = ("fx", "fy", "cx", "cy", "skew", "k1", "k2", "p1", "p2", "k3")
MIN_POINTS_PER_VIEW = 12


@dataclass(frozen=True, eq=False)
class PlaneView:
    """One view of a flat target: points (N, 3) on z = 0 in metres, pixels (N, 2)."""

    obj: np.ndarray
    uv: np.ndarray
    name: str = ""

    def __len__(self) -> int:
        return len(self.uv)


@dataclass(eq=False)
class IntrinsicResult:
    camera: Camera
    rvecs: np.ndarray  # (V, 3) target-to-camera
    tvecs: np.ndarray  # (V, 3)
    rms_px: float
    view_rms_px: np.ndarray  # (V,)
    points: int
    std: dict[str, float]
    coverage: float  # fraction of image cells (8 x 6 grid) holding a point
    residuals: np.ndarray  # (N, 2) px, all views stacked
    inliers: np.ndarray  # (N,) bool: residual within 3 robust sigma
    opencv_rms_px: float = float("nan")
    bias_corrected: bool = False
    extra: dict = field(default_factory=dict)
    # the views as solved (perspective bias removed), in the order of rvecs: what the wand
    # solve takes into its graph (calibkit.calibrate.plane_views)
    views: list = field(default_factory=list)

    def figures(self) -> dict:
        c = self.camera
        return {"fx": c.fx, "fy": c.fy, "cx": c.cx, "cy": c.cy, "skew": c.skew,
                "dist": c.dist.tolist(), "rms_px": self.rms_px, "views": len(self.rvecs),
                "view_rms_px": self.view_rms_px.tolist(), "points": self.points,
                "std": self.std, "coverage": self.coverage,
                "inlier_fraction": float(self.inliers.mean()) if len(self.inliers) else 0.0,
                "opencv_rms_px": self.opencv_rms_px, "bias_corrected": self.bias_corrected,
                "size": list(c.size)}


def camera_figures(camera: Camera) -> dict:
    return {"fx": camera.fx, "fy": camera.fy, "cx": camera.cx, "cy": camera.cy,
            "skew": camera.skew, "dist": camera.dist.tolist()}


def monitor_plane_view(dots, schedule, pixel_pitch_mm: float, name: str = "",
                       min_points: int = MIN_POINTS_PER_VIEW) -> PlaneView:
    """Identified dots (calibkit.calibrate.dotcapture.DotView) -> a PlaneView in metres on the
    screen plane; a UserError when the monitor is (mostly) not in view."""
    moved = getattr(dots, "moved", 0)
    if len(dots) < min_points and moved >= min_points:
        raise UserError(f"the image moved during {name or 'this view'}: {moved} dots shifted "
                        "between frames: hold the camera and the monitor still (a tripod "
                        "for the camera, the monitor resting on something) and retake it")
    if len(dots) < min_points:
        raise UserError(f"the monitor is not in view: only {len(dots)} dots were identified "
                        f"in {name or 'this view'} (need {min_points}); point the camera at "
                        "the screen, dim the room and turn off auto exposure")
    xy = schedule.points_xy[dots.ids] * (pixel_pitch_mm / 1000.0)
    return PlaneView(np.column_stack([xy, np.zeros(len(xy))]), dots.uv, name)


# ---- geometry helpers ---------------------------------------------------------------------

def _rotations(rvecs: np.ndarray) -> np.ndarray:
    return np.stack([rotation_from_rvec(r) for r in rvecs]) if len(rvecs) else np.zeros((0, 3, 3))


def _project(intr: np.ndarray, R: np.ndarray, t: np.ndarray, obj: np.ndarray,
             view: np.ndarray) -> np.ndarray:
    """Pixels of target points; intr = fx fy cx cy skew k1 k2 p1 p2 k3, R (V,3,3), t (V,3)."""
    fx, fy, cx, cy, skew, k1, k2, p1, p2, k3 = intr
    pc = np.einsum("nij,nj->ni", R[view], obj) + t[view]
    x = pc[:, 0] / pc[:, 2]
    y = pc[:, 1] / pc[:, 2]
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return np.column_stack([fx * xd + skew * yd + cx, fy * yd + cy])


def view_normals(rvecs: np.ndarray) -> np.ndarray:
    """The target's normal in each view, in camera coordinates (V, 3)."""
    return _rotations(np.asarray(rvecs))[:, :, 2]


def coverage(uv: np.ndarray, size: tuple[int, int], cells: tuple[int, int] = (8, 6)) -> float:
    """Fraction of an 8 x 6 grid of image cells that hold at least one point."""
    if len(uv) == 0:
        return 0.0
    cx = np.clip((uv[:, 0] + 0.5) / size[0] * cells[0], 0, cells[0] - 1).astype(int)
    cy = np.clip((uv[:, 1] + 0.5) / size[1] * cells[1], 0, cells[1] - 1).astype(int)
    return len(np.unique(cy * cells[0] + cx)) / (cells[0] * cells[1])


def check_views(views: list[PlaneView], min_views: int = 3) -> list[PlaneView]:
    """Views with enough points; a UserError when too few remain."""
    good = [v for v in views if len(v) >= MIN_POINTS_PER_VIEW]
    if len(good) < min_views:
        raise UserError(f"too few usable views: {len(good)} of {len(views)} have at least "
                        f"{MIN_POINTS_PER_VIEW} points, and the solve needs {min_views}; take "
                        "more views with the target well inside the image")
    return good


def _check_tilts(rvecs: np.ndarray) -> None:
    n = view_normals(rvecs)
    spread = np.degrees(np.arccos(np.clip(np.abs(n @ n.T), -1, 1))).max()
    if spread < 5.0:
        raise UserError(f"the views are nearly parallel (they differ by {spread:.1f} degrees "
                        "at most), which leaves the focal length undetermined: tilt the "
                        "target 20-40 degrees about its horizontal and its vertical axis "
                        "between views")


# ---- the solve ------------------------------------------------------------------------------

def _opencv_start(views: list[PlaneView], size: tuple[int, int], fix_k3: bool
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, float]:
    obj = [v.obj.astype(np.float32) for v in views]
    img = [v.uv.astype(np.float32).reshape(-1, 1, 2) for v in views]
    K0 = cv2.initCameraMatrix2D(obj, img, size)
    flags = cv2.CALIB_USE_INTRINSIC_GUESS | (cv2.CALIB_FIX_K3 if fix_k3 else 0)
    try:
        rms, K, dist, rvecs, tvecs = cv2.calibrateCamera(obj, img, size, K0, None, flags=flags)
    except cv2.error as exc:
        raise UserError(f"OpenCV could not calibrate from these views ({exc.err}); take views "
                        "that tilt the target in different directions") from None
    return (K, np.asarray(dist).ravel()[:5], np.asarray(rvecs).reshape(-1, 3),
            np.asarray(tvecs).reshape(-1, 3), float(rms))


def _levenberg_marquardt(residual, jac, x0: np.ndarray, scale_px: float | None,
                         use: np.ndarray | None = None, max_iter: int = 50) -> np.ndarray:
    """Levenberg-Marquardt on the normal equations, robust by iterative reweighting.

    Residuals come in (x, y) pairs, one per point. With `scale_px` each point is weighted
    by the soft-L1 loss on its 2D error, rho(s) = 2 (sqrt(1 + s) - 1), s = (e / scale)^2;
    with None, plain least squares. `use`: mask of the points that count. The normal
    equations have only as many unknowns as the intrinsics and view poses, so they are
    formed and solved directly (an SVD of the full Jacobian, as scipy's exact trust-region
    solver does, costs a hundred times more here).
    """
    def cost_weights(r: np.ndarray) -> tuple[float, np.ndarray]:
        e2 = (r.reshape(-1, 2) ** 2).sum(axis=1)
        if use is not None:
            e2 = np.where(use, e2, 0.0)
        if scale_px is None:
            w = np.ones_like(e2) if use is None else use.astype(np.float64)
            return float(np.dot(e2, w)), w
        z = e2 / scale_px ** 2
        w = 1.0 / np.sqrt(1.0 + z)
        if use is not None:
            w = w * use
        rho = 2.0 * (np.sqrt(1.0 + z) - 1.0) * scale_px ** 2
        return float(rho.sum() if use is None else rho[use].sum()), w

    x = x0.copy()
    r = residual(x)
    cost, w = cost_weights(r)
    lam = 1e-3
    for _ in range(max_iter):
        J = jac(x)
        W = np.repeat(w, 2)
        # einsum, not BLAS: a threaded BLAS on a busy machine is 100x slower for this shape
        A = np.einsum("ni,nj->ij", J, J * W[:, None])
        g = np.einsum("ni,n->i", J, W * r)
        diag = np.maximum(np.diag(A), 1e-12)
        improved = False
        for _ in range(10):
            try:
                dx = -np.linalg.solve(A + lam * np.diag(diag), g)
            except np.linalg.LinAlgError:
                lam *= 10.0
                continue
            r_new = residual(x + dx)
            cost_new, w_new = cost_weights(r_new)
            if np.isfinite(cost_new) and cost_new <= cost:
                x, r, w = x + dx, r_new, w_new
                small = cost - cost_new <= 1e-10 * max(cost, 1e-30)
                cost = cost_new
                lam = max(lam / 10.0, 1e-9)
                improved = True
                break
            lam *= 10.0
        if not improved or small or np.linalg.norm(dx) <= 1e-12 * (1 + np.linalg.norm(x)):
            break
    return x


def refine(intr: np.ndarray, rvecs: np.ndarray, tvecs: np.ndarray, views: list[PlaneView],
           free: np.ndarray, scale_px: float = 0.5):
    """Robust joint refinement of the intrinsics (where `free`) and every view's pose."""
    obj = np.concatenate([v.obj for v in views])
    uv = np.concatenate([v.uv for v in views])
    view = np.concatenate([np.full(len(v), i) for i, v in enumerate(views)])
    nv = len(views)
    fi = np.nonzero(free)[0]
    n_int = len(fi)

    def unpack(x):
        p = intr.copy()
        p[fi] = x[:n_int]
        poses = x[n_int:].reshape(nv, 6)
        return p, poses[:, :3], poses[:, 3:]

    def residual(x):
        p, rv, tv = unpack(x)
        return (_project(p, _rotations(rv), tv, obj, view) - uv).ravel()

    rows2 = np.repeat(view, 2)

    def jac(x):
        """Forward differences grouped by structure: one evaluation per intrinsic, and one
        per pose component for all views at once (a residual sees only its own view).
        Dense: the normal equations are small (intrinsics + 6 per view)."""
        r0 = residual(x)
        J = np.zeros((len(r0), len(x)))
        at = np.arange(len(r0))
        for k in range(n_int + 6):
            dx = np.zeros_like(x)
            if k < n_int:
                h = 1e-7 * max(1.0, abs(x[k]))
                dx[k] = h
                J[:, k] = (residual(x + dx) - r0) / h
            else:
                h = 1e-7
                dx[n_int + (k - n_int)::6] = h
                J[at, n_int + 6 * rows2 + (k - n_int)] = (residual(x + dx) - r0) / h
        return J

    x0 = np.concatenate([intr[fi], np.column_stack([rvecs, tvecs]).ravel()])
    x = _levenberg_marquardt(residual, jac, x0, scale_px)
    res = residual(x).reshape(-1, 2)
    # outliers: beyond 3 robust sigma; then a plain least-squares polish on the inliers,
    # whose Jacobian gives the covariance
    err = np.linalg.norm(res, axis=1)
    sigma_robust = 1.4826 * np.median(np.abs(res)) + 1e-12
    inl = err <= 3.0 * sigma_robust * np.sqrt(2.0) + 1e-9
    x = _levenberg_marquardt(residual, jac, x, None, inl, max_iter=10)
    p, rv, tv = unpack(x)
    res = residual(x).reshape(-1, 2)
    J = jac(x)
    Ji = J[np.repeat(inl, 2)]
    ri = res[inl].ravel()
    dof = max(len(ri) - J.shape[1], 1)
    s2 = float(ri @ ri) / dof
    try:
        cov = np.linalg.inv(np.einsum("ni,nj->ij", Ji, Ji)) * s2
        std_free = np.sqrt(np.clip(np.diag(cov)[:n_int], 0, None))
    except np.linalg.LinAlgError:
        std_free = np.full(n_int, np.inf)
    std = np.zeros(len(intr))
    std[fi] = std_free
    return p, rv, tv, res, inl, std


def disc_bias_px(camera: Camera, rvecs: np.ndarray, tvecs: np.ndarray, views: list[PlaneView],
                 radius_m: float) -> list[np.ndarray]:
    """Per view (N, 2): centroid of the image of a disc minus the image of its centre."""
    out = []
    cam0 = camera.replace(rvec=np.zeros(3), t=np.zeros(3))
    for v, rv, tv in zip(views, rvecs, tvecs, strict=True):
        R = rotation_from_rvec(rv)
        H = np.column_stack([R[:, 0], R[:, 1], tv])  # plane (x, y, 1) -> camera rays
        Hi = np.linalg.inv(H)
        X, Y = v.obj[:, 0], v.obj[:, 1]
        n = len(X)
        C = np.zeros((n, 3, 3))
        C[:, 0, 0] = C[:, 1, 1] = 1.0
        C[:, 0, 2] = C[:, 2, 0] = -X
        C[:, 1, 2] = C[:, 2, 1] = -Y
        C[:, 2, 2] = X * X + Y * Y - radius_m ** 2
        Ci = np.einsum("ji,njk,kl->nil", Hi, C, Hi)  # Hi^T C Hi
        A = Ci[:, :2, :2]
        b = -Ci[:, :2, 2]
        centre = np.linalg.solve(A, b[:, :, None])[:, :, 0]  # normalised image coordinates
        img_c = np.einsum("ij,nj->ni", R, v.obj) + tv
        true = img_c[:, :2] / img_c[:, 2:3]
        out.append(cam0.normalised_to_pixels(centre) - cam0.normalised_to_pixels(true))
    return out


def calibrate(views: list[PlaneView], size: tuple[int, int], name: str = "camera",
              fix_skew: bool = True, fix_k3: bool = False, dot_radius_m: float = 0.0,
              min_views: int = 3) -> IntrinsicResult:
    """Intrinsics from views of a flat target (see the module's docstring)."""
    views = check_views(views, min_views)
    K, dist, rvecs, tvecs, cv_rms = _opencv_start(views, size, fix_k3)
    _check_tilts(rvecs)
    intr = np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2], 0.0, *dist])
    free = np.ones(len(PARAMS), bool)
    free[4] = not fix_skew
    free[9] = not fix_k3
    residual_scale = max(0.5 * cv_rms, 0.02)
    p, rv, tv, res, inl, std = refine(intr, rvecs, tvecs, views, free, scale_px=residual_scale)
    corrected = False
    if dot_radius_m > 0:
        cam = _camera(p, size, name)
        bias = disc_bias_px(cam, rv, tv, views, dot_radius_m)
        views = [PlaneView(v.obj, v.uv - b, v.name) for v, b in zip(views, bias, strict=True)]
        p, rv, tv, res, inl, std = refine(p, rv, tv, views, free, scale_px=residual_scale)
        corrected = True
    cam = _camera(p, size, name)
    counts = np.cumsum([0] + [len(v) for v in views])
    err2 = (res ** 2).sum(axis=1)
    view_rms = np.array([np.sqrt(err2[a:b].mean())
                         for a, b in zip(counts[:-1], counts[1:], strict=True)])
    uv_all = np.concatenate([v.uv for v in views])
    return IntrinsicResult(cam, rv, tv, float(np.sqrt(err2[inl].mean())), view_rms,
                           len(uv_all), dict(zip(PARAMS, std.tolist(), strict=True)),
                           coverage(uv_all, size), res, inl, cv_rms, corrected,
                           views=list(views))


def _camera(p: np.ndarray, size: tuple[int, int], name: str) -> Camera:
    return Camera(name, size, p[0], p[1], p[2], p[3], p[4], p[5:10])


# ---- guidance between views -----------------------------------------------------------------

def view_tilt_deg(obj: np.ndarray, uv: np.ndarray, size: tuple[int, int]) -> tuple[float, float]:
    """Rough tilt of the target about the image's horizontal and vertical axes (degrees),
    from the view's homography and a guessed camera (60 degree field of view), enough to
    say which tilt is missing before any solve."""
    if len(uv) < 8:
        return float("nan"), float("nan")
    H, _ = cv2.findHomography(obj[:, :2], uv, cv2.RANSAC, 3.0)
    if H is None:
        return float("nan"), float("nan")
    f = 0.87 * size[0]
    K = np.array([[f, 0, size[0] / 2], [0, f, size[1] / 2], [0, 0, 1.0]])
    B = np.linalg.inv(K) @ H
    r1 = B[:, 0] / np.linalg.norm(B[:, 0])
    r2 = B[:, 1] / np.linalg.norm(B[:, 1])
    n = np.cross(r1, r2)
    n = n if n[2] > 0 else -n
    return float(np.degrees(np.arctan2(n[1], n[2]))), float(np.degrees(np.arctan2(n[0], n[2])))


def guidance(views: list[PlaneView], size: tuple[int, int], wanted: int) -> str:
    """One line for the user after each view: progress, coverage and the tilt to do next."""
    uv = np.concatenate([v.uv for v in views]) if views else np.zeros((0, 2))
    tilts = np.array([view_tilt_deg(v.obj, v.uv, size) for v in views]).reshape(-1, 2)
    text = (f"{len(views)}/{wanted} views, {len(uv)} points, image coverage "
            f"{100 * coverage(uv, size):.0f}%")
    if len(views) >= wanted:
        return text
    hints = []
    about_x, about_y = tilts[:, 0], tilts[:, 1]
    if not np.any(about_x > 12):
        hints.append("top edge away from the camera")
    elif not np.any(about_x < -12):
        hints.append("top edge towards the camera")
    if not np.any(about_y > 12):
        hints.append("right edge towards the camera")
    elif not np.any(about_y < -12):
        hints.append("right edge away from the camera")
    if coverage(uv, size) < 0.8 and not hints:
        hints.append("the target nearer an image corner not yet covered")
    nxt = "; next: tilt " + " and ".join(hints[:2]) if hints else "; next: any new tilt"
    return text + nxt


# ---- the distortion plot --------------------------------------------------------------------

def distortion_plot_png(result: IntrinsicResult, uv: np.ndarray | None = None) -> bytes:
    """A PNG: the lens distortion's displacement field over the image (arrows, contours
    in pixels) and the measured points, so the user sees how much of the image they covered."""
    # deferred on purpose: loads matplotlib only where used
    import matplotlib

    matplotlib.use("Agg")
    # deferred on purpose: loads matplotlib only where used
    import matplotlib.pyplot as plt

    cam = result.camera
    w, h = cam.size
    gx, gy = np.meshgrid(np.linspace(0, w - 1, 33), np.linspace(0, h - 1, 25))
    pix = np.column_stack([gx.ravel(), gy.ravel()])
    n = cam.undistort(pix)
    ideal = np.column_stack([cam.fx * n[:, 0] + cam.skew * n[:, 1] + cam.cx,
                             cam.fy * n[:, 1] + cam.cy])
    d = pix - ideal
    mag = np.linalg.norm(d, axis=1).reshape(gx.shape)
    fig, ax = plt.subplots(figsize=(8, 8 * h / w + 0.6), dpi=100)
    cs = ax.contour(gx, gy, mag, levels=8, cmap="viridis")
    ax.clabel(cs, fmt="%.1f px", fontsize=7)
    step = 3
    ax.quiver(gx[::step, ::step], gy[::step, ::step], d[:, 0].reshape(gx.shape)[::step, ::step],
              d[:, 1].reshape(gx.shape)[::step, ::step], angles="xy", color="tab:red",
              width=0.002)
    if uv is not None and len(uv):
        ax.plot(uv[:, 0], uv[:, 1], ".", ms=1, color="0.5")
    ax.plot([cam.cx], [cam.cy], "k+", ms=12)
    ax.set_xlim(-0.5, w - 0.5)
    ax.set_ylim(h - 0.5, -0.5)
    ax.set_aspect("equal")
    ax.set_title(f"{cam.name}: distortion (px), RMS {result.rms_px:.3f} px, "
                 f"{result.points} points, coverage {100 * result.coverage:.0f}%", fontsize=9)
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    plt.close(fig)
    return buf.getvalue()
