"""What the live view draws, as pure functions: thumbnails, camera frusta, picking.

The daemon works on blobs: a camera that gives images detects them in its capture thread
and only the blobs go on. So a thumbnail is what the daemon has of the frame: the blobs
drawn on a dark image of the camera's shape (scaled down), with the detection mask and the
threshold written on it. Picking turns a click (a ray) or a dragged rectangle (two screen
corners and the browser's camera) into the markers it meant.
"""

from __future__ import annotations

import cv2
import numpy as np

THUMB_WIDTH_PX = 240


def thumbnail(size: tuple[int, int], uv: np.ndarray, area: np.ndarray,
              threshold: float | str | None = None, mask: np.ndarray | None = None,
              width_px: int = THUMB_WIDTH_PX) -> np.ndarray:
    """(h, w, 3) uint8 RGB: the camera's blobs (pixels, (N, 2)) as discs of their area on
    a dark frame of the camera's shape scaled to `width_px`; masked pixels (mask True:
    ignored by detection) tinted blue; the threshold and blob count written in a corner."""
    w, h = size
    s = width_px / w
    th = max(1, round(h * s))
    img = np.full((th, width_px, 3), 16, np.uint8)
    if mask is not None and mask.any():
        small = cv2.resize(mask.astype(np.uint8), (width_px, th),
                           interpolation=cv2.INTER_NEAREST).astype(bool)
        img[small] = (20, 40, 110)
    uv = np.asarray(uv, np.float64).reshape(-1, 2)
    if len(uv):
        r = np.maximum(np.sqrt(np.maximum(np.asarray(area, np.float64), 1.0) / np.pi) * s, 1.5)
        centres = np.round(uv * s * 16).astype(np.int64)  # 4 bits of sub-pixel precision
        for (x, y), rad in zip(centres.tolist(), np.round(r * 16).astype(int).tolist(),
                               strict=True):
            cv2.circle(img, (x, y), rad, (255, 255, 255), -1, cv2.LINE_AA, shift=4)
            cv2.circle(img, (x, y), rad + 48, (255, 170, 0), 1, cv2.LINE_AA, shift=4)
    label = f"{len(uv)} blobs"
    if threshold is not None:
        label += f"  thr {threshold}"
    cv2.putText(img, label, (4, th - 6), cv2.FONT_HERSHEY_SIMPLEX, 0.38, (190, 190, 190), 1,
                cv2.LINE_AA)
    return img


def wxyz_from_matrix(R: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotation matrices -> (..., 4) quaternions w, x, y, z."""
    # deferred on purpose: loads SciPy's sparse graphs, SciPy's spatial only where used
    from scipy.spatial.transform import Rotation

    q = Rotation.from_matrix(np.asarray(R, np.float64)).as_quat()  # x, y, z, w
    return np.concatenate([q[..., 3:], q[..., :3]], axis=-1)


def camera_frusta(rig) -> list[dict]:
    """Each camera's pose as a frustum: its centre, camera-to-world rotation (w, x, y, z;
    OpenCV's axes, z forward, y down), vertical field of view and aspect."""
    out = []
    for cam in rig:
        fy = float(cam.K[1, 1])
        out.append({"name": cam.name, "position": cam.centre,
                    "wxyz": wxyz_from_matrix(cam.R.T),
                    "fov": 2.0 * np.arctan2(cam.height / 2.0, fy),
                    "aspect": cam.width / cam.height})
    return out


def floor_extent(rig, margin_m: float = 0.5) -> tuple[np.ndarray, float]:
    """Centre (x, y) and side of a square floor under the cameras."""
    c = rig.centres()[:, :2]
    lo, hi = c.min(axis=0) - margin_m, c.max(axis=0) + margin_m
    return (lo + hi) / 2, float(np.max(hi - lo))


def pick_by_ray(xyz: np.ndarray, origin, direction, max_m: float = 0.05,
                max_deg: float = 1.5) -> int:
    """Index of the point nearest the clicked ray (its distance to the ray within max_m, or
    its angle off the ray within max_deg for points far away); -1 for none."""
    xyz = np.asarray(xyz, np.float64).reshape(-1, 3)
    if not len(xyz):
        return -1
    d = np.asarray(direction, np.float64)
    d = d / np.linalg.norm(d)
    rel = xyz - np.asarray(origin, np.float64)
    along = rel @ d
    off = np.linalg.norm(rel - along[:, None] * d, axis=1)
    ok = (along > 0) & ((off <= max_m) | (off <= along * np.tan(np.radians(max_deg))))
    if not ok.any():
        return -1
    return int(np.argmin(np.where(ok, off, np.inf)))


def project_to_screen(xyz: np.ndarray, position, wxyz, fov_rad: float,
                      aspect: float) -> tuple[np.ndarray, np.ndarray]:
    """Points into a browser camera's screen, (0..1, 0..1) from the top left, as viser
    gives it (camera-to-world w, x, y, z in OpenCV's axes, vertical field of view); and
    whether each is in front of it."""
    # deferred on purpose: loads SciPy's sparse graphs, SciPy's spatial only where used
    from scipy.spatial.transform import Rotation

    w, x, y, z = np.asarray(wxyz, np.float64)
    R = Rotation.from_quat([x, y, z, w]).as_matrix()
    p = (np.asarray(xyz, np.float64).reshape(-1, 3) - np.asarray(position)) @ R
    front = p[:, 2] > 1e-6
    zc = np.where(front, p[:, 2], 1.0)
    t = np.tan(fov_rad / 2.0)
    u = 0.5 + p[:, 0] / zc / (2 * t * aspect)
    v = 0.5 + p[:, 1] / zc / (2 * t)
    return np.stack([u, v], axis=1), front


def pick_in_rect(xyz, position, wxyz, fov_rad, aspect, lo, hi) -> np.ndarray:
    """Indices of the points whose screen position lies in the rectangle lo..hi."""
    uv, front = project_to_screen(xyz, position, wxyz, fov_rad, aspect)
    inside = front & np.all((uv >= np.asarray(lo)) & (uv <= np.asarray(hi)), axis=1)
    return np.flatnonzero(inside)


def markerset_sticks(ms) -> list[tuple[int, int]]:
    """The sticks drawn between a marker set's markers: within each segment, each marker
    to its nearest neighbour and the neighbours joined into one tree (a minimum spanning
    tree of the segment's reference shape), so a segment reads as one piece."""
    # deferred on purpose: loads SciPy's sparse graphs only where used
    from scipy.sparse.csgraph import minimum_spanning_tree

    sticks = []
    for seg in ms.segments:
        idx = list(seg.markers)
        if len(idx) < 2:
            continue
        shape = np.asarray(seg.shape_m, np.float64)
        d = np.linalg.norm(shape[:, None] - shape[None], axis=2) + 1e-9
        tree = minimum_spanning_tree(np.triu(d, 1)).tocoo()
        sticks += [(idx[a], idx[b]) for a, b in zip(tree.row, tree.col, strict=True)]
    return sticks


def markerset_segments(ms) -> list[int]:
    """The segment of each of a marker set's markers (-1 for a marker on none): labelled
    markers are coloured by it."""
    out = [-1] * len(ms.labels)
    for k, seg in enumerate(ms.segments):
        for m in seg.markers:
            out[int(m)] = k
    return out


def trail_segments(history: np.ndarray) -> np.ndarray:
    """(n, 3) positions over time -> (n-1, 2, 3) line segments, gaps (NaN) left out."""
    h = np.asarray(history, np.float32).reshape(-1, 3)
    if len(h) < 2:
        return np.zeros((0, 2, 3), np.float32)
    seg = np.stack([h[:-1], h[1:]], axis=1)
    return seg[np.isfinite(seg).all(axis=(1, 2))]
