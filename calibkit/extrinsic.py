"""Camera poses from dots a ceiling projector casts on the floor and on a table top.

All cameras see the same projected dot at the same moment, so once we know where a
projector pixel lands in the world, each dot is a known world point for every camera that
sees it. Where a pixel lands comes from a few reference dots the user measures with a
tape: a homography projector -> floor (and one projector -> table top, at the table's
measured height). Floor points alone fix a camera well near the floor but poorly above it
(a small tilt error grows with height); the table's plane, 0.75 m up, pins the cameras at
head height too.

Steps (each a pure function here; capture talks to a device through `ProjectorRig`):
references -> plane maps -> coded dot capture per session (floor, then table), every
camera settling on its own -> dots identified by the code -> world points -> per camera
PnP with RANSAC on floor + table points -> refinement -> a joint refinement of all cameras
(the dots are shared, so cameras must agree on them) -> per-camera figures.
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol

import cv2
import numpy as np

from calibkit.camera import Camera, Rig
from calibkit.detect import DetectorConfig, detect
from calibkit.errors import UserError
from calibkit.geometry import RigArrays, mean_ray_distance, triangulate
from calibkit.settle import SettleDetector, signature_noise
from projector.display import Dots
from projector.patterns import (
    ROLE_OFF,
    Schedule,
    name_layers,
)

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib  # type: ignore[no-redef]

FLOOR, TABLE = 0, 1
MIN_REFERENCES = 4


# ---- reference points ---------------------------------------------------------------------------

@dataclass(frozen=True, eq=False)
class References:
    """Reference dots measured by hand: projector pixels (N, 2) and where they landed (N, 2),
    metres in the world frame (x, y on the floor; on the table top, at table_height_m)."""

    floor_px: np.ndarray
    floor_xy_m: np.ndarray
    table_px: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    table_xy_m: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    table_height_m: float | None = None
    table_corners_xy_m: np.ndarray | None = None  # the table top's outline, if measured
    projector_size: tuple[int, int] = (1280, 800)

    @property
    def has_table(self) -> bool:
        return len(self.table_px) > 0 or self.table_height_m is not None


def reference_layout_px(projector_size: tuple[int, int], n: int = 4,
                        inset: float = 0.1) -> np.ndarray:
    """Where to put the reference dots: an n x n grid inset from the projector's edges
    (spread wide: the homography is steadiest when the points surround the dots). The
    world frame's yaw is only as good as these points: with 5 mm tape error the worst of 10
    simulated scenes was 0.106 degrees with 9 points, 0.072 with 16 (docs/extrinsic.md)."""
    w, h = projector_size
    xs = np.linspace(inset * (w - 1), (1 - inset) * (w - 1), n)
    ys = np.linspace(inset * (h - 1), (1 - inset) * (h - 1), n)
    gx, gy = np.meshgrid(xs, ys)
    return np.rint(np.column_stack([gx.ravel(), gy.ravel()]))


def _pairs(doc: dict, key: str, path: Path) -> tuple[np.ndarray, np.ndarray]:
    rows = doc.get(key, [])
    if not isinstance(rows, list):
        raise UserError(f"{path}: '{key}' must be a list of {{px = [u, v], xy_m = [x, y]}}")
    px, xy = [], []
    for i, row in enumerate(rows):
        try:
            p = np.asarray(row["px"], float).reshape(2)
            q = np.asarray(row["xy_m"], float).reshape(2)
        except (KeyError, TypeError, ValueError):
            raise UserError(f"{path}: {key} point {i + 1} needs px = [u, v] and "
                            "xy_m = [x, y] (two numbers each)") from None
        if not (np.isfinite(p).all() and np.isfinite(q).all()):
            raise UserError(f"{path}: {key} point {i + 1} holds a value that is not a number")
        px.append(p)
        xy.append(q)
    return np.array(px).reshape(-1, 2), np.array(xy).reshape(-1, 2)


def load_references(path: str | Path) -> References:
    """Read a reference-points TOML file (format: docs/extrinsic.md)."""
    path = Path(path)
    if not path.exists():
        raise UserError(f"{path}: no such reference-points file")
    try:
        with open(path, "rb") as handle:
            doc = tomllib.load(handle)
    except tomllib.TOMLDecodeError as exc:
        raise UserError(f"{path}: not valid TOML ({exc})") from None
    size = doc.get("projector", {}).get("size", [1280, 800])
    try:
        w, h = (int(v) for v in size)
    except (TypeError, ValueError):
        raise UserError(f"{path}: projector.size must be [width, height] in pixels") from None
    floor_px, floor_xy = _pairs(doc, "floor", path)
    table = doc.get("table", {})
    if not isinstance(table, dict):
        raise UserError(f"{path}: [table] must be a table with height_m and [[table.point]]")
    table_px, table_xy = _pairs(table, "point", path)
    height = table.get("height_m")
    if height is not None and (not isinstance(height, (int, float)) or not 0 < height < 3):
        raise UserError(f"{path}: table.height_m must be a height in metres between 0 and 3, "
                        f"got {height!r}")
    corners = table.get("corners_xy_m")
    if corners is not None:
        try:
            corners = np.asarray(corners, float).reshape(-1, 2)
        except (TypeError, ValueError):
            raise UserError(f"{path}: table.corners_xy_m must be a list of [x, y]") from None
    refs = References(floor_px, floor_xy, table_px, table_xy,
                      None if height is None else float(height), corners, (w, h))
    check_references(refs, str(path))
    return refs


def check_references(refs: References, where: str = "reference points") -> None:
    """Enough, well spread points for each plane; a table needs its height."""
    if len(refs.floor_px) < MIN_REFERENCES:
        raise UserError(f"{where}: {len(refs.floor_px)} floor reference points given, at least "
                        f"{MIN_REFERENCES} are needed (measure where 4 or more reference dots "
                        "land on the floor)")
    if len(refs.table_px) and refs.table_height_m is None:
        raise UserError(f"{where}: table points are given but not the table's height: add "
                        "height_m = ... (metres, floor to table top) under [table]")
    if refs.table_height_m is not None and len(refs.table_px) < MIN_REFERENCES:
        raise UserError(f"{where}: {len(refs.table_px)} table reference points given, at least "
                        f"{MIN_REFERENCES} are needed on the table top")


def references_toml(refs: References, comment: str = "") -> str:
    """The reference-points file for `refs` (a template when xy values are NaN)."""
    def pair(p, q):
        qs = "nan, nan" if not np.isfinite(q).all() else f"{q[0]:.4f}, {q[1]:.4f}"
        return f"px = [{p[0]:.1f}, {p[1]:.1f}]\nxy_m = [{qs}]\n"

    lines = [f"# {line}" for line in comment.splitlines()] if comment else []
    lines.append(f"[projector]\nsize = [{refs.projector_size[0]}, {refs.projector_size[1]}]\n")
    for p, q in zip(refs.floor_px, refs.floor_xy_m, strict=True):
        lines.append("[[floor]]\n" + pair(p, q))
    if refs.table_height_m is not None:
        lines.append(f"[table]\nheight_m = {refs.table_height_m:.4f}\n")
        for p, q in zip(refs.table_px, refs.table_xy_m, strict=True):
            lines.append("[[table.point]]\n" + pair(p, q))
    return "\n".join(lines)


# ---- plane maps ---------------------------------------------------------------------------------

@dataclass(frozen=True, eq=False)
class PlaneMap:
    """Projector pixels -> a horizontal plane at height_m: homography H (3x3); the fit's RMS
    and largest residual at the reference points (mm; 0 with exactly 4 points, which fit any
    homography exactly and so check nothing); the plane's outline (K, 2) for the table."""

    H: np.ndarray
    height_m: float
    residual_rms_mm: float
    residual_max_mm: float
    n_points: int
    outline_xy_m: np.ndarray | None = None

    def apply(self, px: np.ndarray) -> np.ndarray:
        """Projector pixels (N, 2) -> world points (N, 3) on the plane."""
        px = np.asarray(px, float).reshape(-1, 2)
        h = np.column_stack([px, np.ones(len(px))]) @ self.H.T
        with np.errstate(divide="ignore", invalid="ignore"):
            xy = h[:, :2] / h[:, 2:3]
        return np.column_stack([xy, np.full(len(px), self.height_m)])


def fit_homography(px: np.ndarray, xy_m: np.ndarray, height_m: float = 0.0,
                   what: str = "floor") -> PlaneMap:
    """Least-squares homography projector px -> plane xy (Hartley-normalised DLT, then
    refined on the metric residual). Points on a line, or repeated, cannot fix it."""
    px = np.asarray(px, float).reshape(-1, 2)
    xy = np.asarray(xy_m, float).reshape(-1, 2)
    if len(px) < MIN_REFERENCES:
        raise UserError(f"{what}: {len(px)} reference points, at least {MIN_REFERENCES} needed")
    for pts, unit in ((px, "projector pixels"), (xy, "measured positions")):
        c = pts - pts.mean(axis=0)
        s = np.linalg.svd(c, compute_uv=False)
        if s[1] < 1e-3 * max(s[0], 1e-12):
            raise UserError(f"{what}: the reference points lie on a line ({unit}): spread "
                            "them over the area, e.g. near its corners")
    H, _ = cv2.findHomography(px, xy, 0)
    if H is None:
        raise UserError(f"{what}: the reference points do not fit a homography: check that "
                        "each measured position belongs to its projector pixel")
    # refine the metric residual (findHomography's least squares is algebraic)
    from scipy.optimize import least_squares

    def resid(h):
        m = np.append(h, 1.0).reshape(3, 3)
        q = np.column_stack([px, np.ones(len(px))]) @ m.T
        return (q[:, :2] / q[:, 2:3] - xy).ravel()

    H = H / H[2, 2]
    sol = least_squares(resid, H.ravel()[:8], method="lm" if len(px) > 4 else "trf")
    H = np.append(sol.x, 1.0).reshape(3, 3)
    r = np.linalg.norm(resid(sol.x).reshape(-1, 2), axis=1) * 1000.0
    return PlaneMap(H, float(height_m), float(np.sqrt(np.mean(r**2))), float(r.max()), len(px))


def plane_maps(refs: References) -> tuple[PlaneMap, PlaneMap | None]:
    """The floor map and, with table points, the table-top map (outline: the corners if
    measured, else the hull of the table's reference points)."""
    check_references(refs)
    floor = fit_homography(refs.floor_px, refs.floor_xy_m, 0.0, "floor")
    if refs.table_height_m is None:
        return floor, None
    table = fit_homography(refs.table_px, refs.table_xy_m, refs.table_height_m, "table")
    outline = refs.table_corners_xy_m
    if outline is None or len(outline) < 3:
        outline = refs.table_xy_m
    hull = cv2.convexHull(np.asarray(outline, np.float32)).reshape(-1, 2).astype(float)
    return floor, PlaneMap(table.H, table.height_m, table.residual_rms_mm,
                           table.residual_max_mm, table.n_points, hull)


def _inside(poly: np.ndarray, xy: np.ndarray, margin_m: float) -> np.ndarray:
    """Points at least margin_m inside a convex polygon (negative margin: outside allowed)."""
    c = cv2.convexHull(np.asarray(poly, np.float32)).reshape(-1, 2).astype(float)
    return _signed_distance(c, np.asarray(xy, float).reshape(-1, 2)) >= margin_m


def _signed_distance(poly: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Signed distance to a convex polygon's edges (positive inside), vectorised."""
    a = poly
    b = np.roll(poly, -1, axis=0)
    e = b - a
    n = np.column_stack([-e[:, 1], e[:, 0]]) / np.linalg.norm(e, axis=1, keepdims=True)
    centre = poly.mean(axis=0)
    flip = np.sign(np.sum((centre - a) * n, axis=1))
    n = n * flip[:, None]  # inward normals
    return np.min(np.einsum("pkj,kj->pk", xy[:, None, :] - a[None], n), axis=1)


def dot_world_points(px: np.ndarray, floor: PlaneMap | None, table: PlaneMap | None,
                     table_session: bool, edge_margin_m: float = 0.03
                     ) -> tuple[np.ndarray, np.ndarray]:
    """World points (N, 3) and plane ids (N,) of projector pixels in a session: in the floor
    session every dot is on the floor; in the table session the dots landing on the table
    top (at least edge_margin_m inside its outline) are table points and every other dot is
    dropped (-1): it lands on the floor, already measured, or on the table's edge."""
    px = np.asarray(px, float).reshape(-1, 2)
    if not table_session:
        assert floor is not None
        return floor.apply(px), np.zeros(len(px), np.int64)
    if table is None:
        raise UserError("the table session needs the table's reference points and height")
    xyz = table.apply(px)
    on = _inside(table.outline_xy_m, xyz[:, :2], edge_margin_m)
    return xyz, np.where(on, TABLE, -1)


def table_schedule(schedule: Schedule, table: PlaneMap, edge_margin_m: float = 0.03
                   ) -> Schedule:
    """The schedule's dots that land on the table top (by the table map, edge_margin_m
    inside its outline), coded afresh. Showing only these keeps every camera's image of the
    dots one smooth plane: dots on the floor beside the table would sit next to table dots
    in the image but far from them in depth, and naming dots from their neighbours assumes
    a smooth map from the projector to the image."""
    from projector.patterns import ROLE_BIT, ROLE_ON, PatternFrame, code_bits

    _, plane = dot_world_points(schedule.points_xy, None, table, True, edge_margin_m)
    keep = plane == TABLE
    layers = [ids[keep[ids]] for ids in schedule.layers]
    layers = [ids for ids in layers if len(ids)]
    if not layers:
        raise UserError("no dot of the pattern lands on the table top: check the table's "
                        "reference points (are they on the table?) or use a finer --step")
    n_bits = max(1, int(np.ceil(np.log2(max(max(len(ids) for ids in layers), 2)))))
    frames = []
    for layer, ids in enumerate(layers):
        xy = schedule.points_xy[ids]
        frames.append(PatternFrame(xy, ids, layer, ROLE_ON))
        if layer > 0:
            continue
        frames.append(PatternFrame(xy[:0], ids[:0], layer, ROLE_OFF))
        bits = code_bits(np.arange(len(ids)), n_bits)
        for b in range(n_bits + 1):
            frames.append(PatternFrame(xy[bits[:, b]], ids[bits[:, b]], layer, ROLE_BIT, b))
    return Schedule(schedule.screen_px, schedule.points_xy, layers, frames, n_bits,
                    schedule.radius_px, schedule.step_px, "coded",
                    {**schedule.meta, "table_only": True})


# ---- capture ------------------------------------------------------------------------------------

class ProjectorRig(Protocol):
    """What capture needs from hardware: the projector shows dots, every camera delivers
    its next frame (one image per camera, in rig order)."""

    def show(self, dots: Dots) -> None: ...

    def grab(self) -> list[np.ndarray]: ...


@dataclass(frozen=True, eq=False)
class CameraDots:
    """Identified dots of one camera in one session: point ids (N,), image positions
    (N, 2) px, their scatter over the samples (N,) px; rejected: detections not named."""

    ids: np.ndarray
    uv: np.ndarray
    scatter_px: np.ndarray
    rejected: int = 0

    def __len__(self) -> int:
        return len(self.ids)


@dataclass(frozen=True, eq=False)
class SessionCapture:
    """A session's dots per camera, the camera frames it took and each camera's latency
    (frames from a pattern change to the first changed image; None if never seen)."""

    cameras: list[CameraDots]
    frames: int
    latency_frames: list[int | None]


def _gray(image: np.ndarray) -> np.ndarray:
    img = np.asarray(image)
    if img.ndim == 3:
        img = img[:, :, :3].astype(np.float32) @ np.array([0.114, 0.587, 0.299], np.float32)
    return img.astype(np.float32)


def capture_session(device: ProjectorRig, schedule: Schedule, n_cameras: int,
                    samples: int = 3, hold: int = 1, max_settle_frames: int = 60,
                    max_scatter_px: float = 0.3, progress=None,
                    latency_frames: list[int | None] | None = None) -> SessionCapture:
    """Run the schedule once with every camera watching.

    Each camera has its own SettleDetector (latencies differ): after the projector changes,
    a camera's samples are the first `samples` frames once its own image has settled; the
    projector moves on when every camera has them. The first pattern (every dot on) teaches
    each camera its latency; later, a camera whose image does not change (none of its dots
    changed) is done once the others are and its own latency has passed; one that never
    settles gives no image for that pattern (a missing bit, which the parity may restore).
    latency_frames: each camera's latency from an earlier session (the table session reuses
    the floor's: a camera that sees the table top at a grazing angle barely changes).
    """
    # a blank first: long enough for the slowest camera to stop showing what was there
    # before (12 frames = 400 ms at 30 fps when no latency is known), then 5 still frames
    # for the noise level
    device.show(Dots.make(np.zeros((0, 2))))
    known = [int(v) for v in (latency_frames or []) if v is not None]
    warm = [device.grab() for _ in range(max(12, max(known, default=0) + hold + 2) + 5)]
    frames = len(warm)
    settle = []
    for c in range(n_cameras):
        noise = signature_noise([w[c] for w in warm[-5:]])
        det = SettleDetector(noise=noise, hold=hold, max_wait_frames=max_settle_frames)
        if latency_frames is not None and latency_frames[c] is not None:
            det.latencies.append(int(latency_frames[c]))  # learnt in an earlier session
        det.start(warm[-1][c])
        settle.append(det)
    step_images: list[dict[int, np.ndarray | None]] = [{} for _ in range(n_cameras)]
    on_shots: list[dict[int, list[np.ndarray]]] = [{} for _ in range(n_cameras)]
    for i, frame in enumerate(schedule.frames):
        device.show(Dots.make(frame.xy, schedule.radius_px))
        for det in settle:
            det.start()
        shots: list[list[np.ndarray]] = [[] for _ in range(n_cameras)]
        changed = [False] * n_cameras
        waited = 0
        while waited < max_settle_frames + samples:
            images = device.grab()
            frames += 1
            waited += 1
            for c in range(n_cameras):
                if len(shots[c]) >= samples:
                    continue
                before = len(settle[c].latencies)
                ok = settle[c].feed(images[c])
                changed[c] |= len(settle[c].latencies) > before
                if ok:
                    shots[c].append(_gray(images[c]))
            done = [len(s) >= samples for s in shots]
            if all(done):
                break
            # the cameras that saw a change are done, and each other camera's latency (its
            # own, else the slowest known) has passed: they see nothing of this pattern.
            # Not on the first pattern (all dots on), where every camera learns its latency.
            lat = [d.latency_frames for d in settle if d.latency_frames is not None]
            if any(changed) and all(d for d, ch in zip(done, changed, strict=True) if ch) \
                    and all(_latency_passed(settle[c].latency_frames, lat, i == 0, waited, hold)
                            for c in range(n_cameras) if not done[c]):
                for c in range(n_cameras):
                    if not done[c] and not changed[c]:
                        shots[c] = [_gray(images[c])] * samples
                break
        for c in range(n_cameras):
            if len(shots[c]) >= samples:
                step_images[c][i] = np.mean(shots[c][:samples], axis=0)
                on_shots[c][i] = shots[c][:samples]
            else:
                step_images[c][i] = None
        if progress is not None:
            progress(i + 1, len(schedule.frames))
    cams = [identify_dots(schedule, step_images[c], on_shots[c], max_scatter_px)
            for c in range(n_cameras)]
    return SessionCapture(cams, frames, [d.latency_frames for d in settle])


def _latency_passed(own: int | None, known: list[int], first: bool, waited: int,
                    hold: int) -> bool:
    """Has a camera whose image did not change waited past its latency (its own, else the
    slowest known; never on the first pattern when it has none)?"""
    if own is None and (first or not known):
        return False
    return waited > (own if own is not None else max(known)) + hold + 2


def _nearest(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    if len(b) == 0:
        return np.zeros(len(a), np.int64), np.full(len(a), np.inf)
    from scipy.spatial import cKDTree

    d, i = cKDTree(b).query(a)
    return np.asarray(i, np.int64), np.asarray(d, np.float64)


def find_dots(on: np.ndarray, off: np.ndarray, shots: list[np.ndarray],
              max_scatter_px: float = 0.3) -> tuple[np.ndarray, np.ndarray]:
    """Dots in (on - off): centroids, and their scatter over the single samples; dots that
    moved, or are much smaller than their peers (cut by an edge), are dropped."""
    cfg = DetectorConfig(threshold="auto", min_area=2.0, max_area=2000.0, min_roundness=0.4)
    blobs = detect(on - off, cfg)
    if len(blobs) == 0:
        return np.zeros((0, 2)), np.zeros(0)
    uv = blobs.uv
    keep = blobs.area >= 0.4 * np.median(blobs.area)
    per_shot = []
    for shot in shots:
        b = detect(shot - off, cfg.replace(threshold=blobs.threshold))
        j, d = _nearest(uv, b.uv)
        p = np.full_like(uv, np.nan)
        p[d < 1.0] = b.uv[j[d < 1.0]]
        per_shot.append(p)
    stack = np.stack(per_shot)
    with np.errstate(invalid="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # a dot missing from every sample
        spread = np.sqrt(np.nanmean(np.sum((stack - uv) ** 2, axis=2), axis=0)) \
            if len(shots) > 1 else np.zeros(len(uv))
    keep &= np.isfinite(stack).all(axis=(0, 2)) & (spread <= max_scatter_px)
    return uv[keep], spread[keep]


def identify_dots(schedule: Schedule, step_images: dict[int, np.ndarray | None],
                  on_shots: dict[int, list[np.ndarray]], max_scatter_px: float = 0.3
                  ) -> CameraDots:
    """Name every dot one camera saw: the first layer by its code (checked against its
    neighbours), later layers by where the named dots around them put them."""
    ids, uv, scatter, rejected = name_layers(
        schedule, step_images,
        lambda i, on, off: find_dots(on, off, on_shots[i], max_scatter_px))
    ids_a = np.concatenate(ids) if ids else np.zeros(0, np.int64)
    uv_a = np.concatenate(uv) if uv else np.zeros((0, 2))
    sc_a = np.concatenate(scatter) if scatter else np.zeros(0)
    uniq, counts = np.unique(ids_a, return_counts=True)
    dup = np.isin(ids_a, uniq[counts > 1])  # named twice: one of them is wrong
    return CameraDots(ids_a[~dup], uv_a[~dup], sc_a[~dup], rejected + int(dup.sum()))


def capture_frames_estimate(schedule: Schedule, latency_frames: list[int], samples: int = 3,
                            hold: int = 1) -> int:
    """Camera frames a session takes when the slowest camera settles `max(latency) + hold`
    frames after each change (what capture_session does, without images)."""
    per = max(latency_frames) + hold + samples
    return 8 + len(schedule.frames) * per


# ---- poses --------------------------------------------------------------------------------------

@dataclass(frozen=True)
class SolveOptions:
    min_dots: int = 12  # fewer dots than this: the camera is not calibrated
    min_table_dots: int = 6  # fewer table dots: "one plane only" warning
    ransac_px: float = 3.0
    outlier_sigmas: float = 4.0
    joint: bool = True  # refine all cameras together on the shared dots
    reference_sigma_m: float = 0.005  # how well the plane maps place a dot (joint solve)
    height_sigma_m: float = 0.002  # how well the table height is known (joint solve)


@dataclass(frozen=True, eq=False)
class DotObservations:
    """Every identified dot of both sessions, one row per (camera, dot): the multi-camera
    observations of points on known planes that the calibration (and the wand bundle)
    uses. point: dot index into xyz/plane; xyz: the dots' world points from the plane maps."""

    camera_names: tuple[str, ...]
    camera: np.ndarray  # (M,) index into camera_names
    point: np.ndarray  # (M,)
    uv: np.ndarray  # (M, 2) distorted pixels
    xyz: np.ndarray  # (P, 3)
    plane: np.ndarray  # (P,) FLOOR or TABLE
    plane_height_m: tuple[float, float]  # floor, table (NaN without a table)

    def __len__(self) -> int:
        return len(self.camera)

    def select(self, mask: np.ndarray) -> DotObservations:
        return DotObservations(self.camera_names, self.camera[mask], self.point[mask],
                               self.uv[mask], self.xyz, self.plane, self.plane_height_m)


def assemble(camera_names, floor_dots: list[CameraDots], table_dots: list[CameraDots] | None,
             schedule: Schedule, floor: PlaneMap, table: PlaneMap | None) -> DotObservations:
    """Both sessions' dots with world points: floor-session dot k is point k, table-session
    dot k is point P + k (P: the schedule's points); dots that land nowhere usable go."""
    n = len(schedule.points_xy)
    f_xyz, f_plane = dot_world_points(schedule.points_xy, floor, table, False)
    xyz, plane = [f_xyz], [f_plane]
    if table_dots is not None:
        t_xyz, t_plane = dot_world_points(schedule.points_xy, floor, table, True)
        xyz.append(t_xyz)
        plane.append(t_plane)
    xyz_a, plane_a = np.concatenate(xyz), np.concatenate(plane)
    cam, pt, uv = [], [], []
    for s, dots in enumerate([floor_dots] + ([table_dots] if table_dots is not None else [])):
        for c, d in enumerate(dots):
            p = d.ids + s * n
            ok = plane_a[p] >= 0
            cam.append(np.full(int(ok.sum()), c))
            pt.append(p[ok])
            uv.append(d.uv[ok])
    heights = (0.0, table.height_m if table is not None else math.nan)
    return DotObservations(tuple(camera_names), np.concatenate(cam).astype(np.int64),
                           np.concatenate(pt).astype(np.int64),
                           np.concatenate(uv).reshape(-1, 2), xyz_a, plane_a, heights)


@dataclass(frozen=True, eq=False)
class PoseResult:
    """One camera's pose solve: the camera (None if not calibrated), which of its rows were
    inliers, the figures and, when something is wrong, a message for the user."""

    name: str
    camera: Camera | None
    inlier: np.ndarray
    rms_px: float
    floor_dots: int
    table_dots: int
    warning: str = ""


def _pnp(cam: Camera, xyz: np.ndarray, uv: np.ndarray, opts: SolveOptions
         ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """RANSAC on every dot, then Levenberg-Marquardt on the inliers, then inliers again by
    the refined pose's residuals: (rvec, t, inlier mask)."""
    K, dist = cam.K, cam.dist
    obj = np.ascontiguousarray(xyz, np.float64)
    img = np.ascontiguousarray(uv, np.float64)
    ok, rvec, tvec, inl = cv2.solvePnPRansac(obj, img, K, dist, iterationsCount=500,
                                             reprojectionError=opts.ransac_px,
                                             confidence=0.999, flags=cv2.SOLVEPNP_SQPNP)
    if not ok or inl is None or len(inl) < 6:
        return None
    inlier = np.zeros(len(obj), bool)
    inlier[inl.ravel()] = True
    for _ in range(3):
        rvec, tvec = cv2.solvePnPRefineLM(obj[inlier], img[inlier], K, dist, rvec, tvec)
        proj, _ = cv2.projectPoints(obj, rvec, tvec, K, dist)
        r = np.linalg.norm(proj.reshape(-1, 2) - img, axis=1)
        sigma = np.median(r[inlier]) / 1.1774  # a 2D Gaussian's norm has median 1.1774 sigma
        new = r <= max(opts.outlier_sigmas * sigma, 0.5)
        if np.array_equal(new, inlier) or new.sum() < 6:
            break
        inlier = new
    return rvec.ravel(), tvec.ravel(), inlier


def solve_camera(cam: Camera, xyz: np.ndarray, plane: np.ndarray, uv: np.ndarray,
                 opts: SolveOptions = SolveOptions()) -> PoseResult:
    """A camera's pose from its dots (world points (N, 3) on plane ids (N,), pixels)."""
    n_floor, n_table = int(np.sum(plane == FLOOR)), int(np.sum(plane == TABLE))
    none = np.zeros(len(uv), bool)
    if len(uv) < opts.min_dots:
        what = "no projected dot" if len(uv) == 0 else f"only {len(uv)} projected dots"
        return PoseResult(cam.name, None, none, math.nan, n_floor, n_table,
                          f"camera {cam.name} saw {what} (needs {opts.min_dots}): not "
                          "calibrated; turn it towards the floor the projector lights, or "
                          "move the projector so its dots reach the camera's view")
    sol = _pnp(cam, xyz, uv, opts)
    if sol is None:
        return PoseResult(cam.name, None, none, math.nan, n_floor, n_table,
                          f"camera {cam.name}: no pose fits its {len(uv)} dots (are its "
                          "intrinsics right? is the reference-points file for this "
                          "projector?): not calibrated")
    rvec, t, inlier = sol
    solved = cam.replace(rvec=rvec, t=t)
    proj, _ = solved.project(xyz[inlier])
    rms = float(np.sqrt(np.mean(np.sum((proj - uv[inlier]) ** 2, axis=1))))
    fi = int(np.sum(inlier & (plane == FLOOR)))
    ti = int(np.sum(inlier & (plane == TABLE)))
    warning = ""
    if ti < opts.min_table_dots or fi < opts.min_table_dots:
        seen, unseen = ("floor", "table") if ti < opts.min_table_dots else ("table", "floor")
        warning = (f"camera {cam.name} saw the {seen} dots but only "
                   f"{ti if seen == 'floor' else fi} on the {unseen}: calibrated from one "
                   f"plane, less accurate away from it; turn the camera to see the {unseen} "
                   "too (or move the table into its view)")
    return PoseResult(cam.name, solved, inlier, rms, fi, ti, warning)


def _joint(rig: Rig, dots: DotObservations, use: np.ndarray, opts: SolveOptions
           ) -> tuple[Rig, np.ndarray]:
    """All calibrated cameras at once on the shared dots (calibkit.bundle): each dot is a
    free point held on its plane (sigma height_sigma_m) and near where the plane maps put it
    (sigma reference_sigma_m), so the cameras must agree with each other, not only with the
    maps. Returns the rig and the refined dot positions (NaN where a dot was not used)."""
    from calibkit import bundle

    sel = dots.select(use)
    index = np.array([rig.names.index(n) if n in rig.names else -1 for n in dots.camera_names])
    used = np.unique(sel.point[index[sel.camera] >= 0])
    data = bundle_data(rig, sel)
    result = bundle.solve(data, bundle.BundleOptions(
        noise_px=0.3, known_sigma_m=opts.reference_sigma_m, plane_sigma_m=opts.height_sigma_m,
        rounds=1, max_iterations=50))
    refined = np.full_like(dots.xyz, np.nan)
    refined[used] = result.xyz
    return result.rig, refined


def bundle_data(rig: Rig, dots: DotObservations, known: bool = True):
    """The dots as calibkit.bundle input for `rig` (cameras matched by name): every dot a
    point observed by its cameras, held on its plane (n = z, d = height) and, with `known`,
    near its plane-map position (known_point). To join them to a wand solve, append these
    rows (points renumbered after the wand's) to its BundleData."""
    from calibkit import bundle

    index = np.array([rig.names.index(n) if n in rig.names else -1
                      for n in dots.camera_names])
    rows = index[dots.camera] >= 0
    used, point = np.unique(dots.point[rows], return_inverse=True)
    xyz = dots.xyz[used]
    heights = np.array(dots.plane_height_m)[dots.plane[used]]
    normals = np.tile([0.0, 0.0, 1.0], (len(used), 1))
    pts = np.arange(len(used))
    return bundle.BundleData(
        rig, point, index[dots.camera[rows]], dots.uv[rows], xyz,
        known_point=pts if known else np.zeros(0, np.int64),
        known_xyz=xyz if known else np.zeros((0, 3)),
        plane_point=pts, plane_normal=normals, plane_offset_m=heights)


@dataclass(eq=False)
class ExtrinsicResult:
    rig: Rig  # the calibrated cameras only
    poses: list[PoseResult]
    dots: DotObservations  # every identified dot (all cameras)
    inlier: np.ndarray  # (len(dots),) rows used
    refined_xyz: np.ndarray  # (P, 3) dots after the joint solve (plane-map points without it)
    report: dict
    warnings: list[str]


def calibrate(intrinsics: Rig, dots: DotObservations, floor: PlaneMap,
              table: PlaneMap | None, opts: SolveOptions = SolveOptions()) -> ExtrinsicResult:
    """Every camera's pose from its dots; cameras that cannot be placed are left out with
    a warning. Raises UserError when none can be placed."""
    absent = [n for n in dots.camera_names if n not in intrinsics.names]
    if absent:
        raise UserError(f"camera '{absent[0]}' has no intrinsics in the rig file (it has "
                        f"{', '.join(intrinsics.names)})")
    poses, messages = [], []
    if table is None:
        opts = dataclasses.replace(opts, min_table_dots=0)
        messages.append("no table: every camera is calibrated from the floor alone, less "
                        "accurate at head height; add the table (docs/extrinsic.md)")
    inlier = np.zeros(len(dots), bool)
    for c, name in enumerate(dots.camera_names):
        rows = np.flatnonzero(dots.camera == c)
        p = dots.point[rows]
        res = solve_camera(intrinsics[name], dots.xyz[p], dots.plane[p], dots.uv[rows], opts)
        poses.append(res)
        inlier[rows[res.inlier]] = True
        if res.warning:
            messages.append(res.warning)
    placed = [r.camera for r in poses if r.camera is not None]
    if not placed:
        why = ", ".join(f"{r.name} {r.warning.split(': ')[0].split(' ', 2)[2]}"
                        .replace(f" (needs {opts.min_dots})", "") for r in poses)
        raise UserError(f"no camera could be calibrated ({why}): each needs "
                        f"{opts.min_dots} identified dots; turn the cameras towards the "
                        "floor the projector lights, and check --intrinsics and --refs")
    rig = Rig(tuple(placed))
    refined = dots.xyz
    if opts.joint and len(placed) >= 2:
        rig, refined = _joint(rig, dots, inlier, opts)
        poses = [_refigure(r, rig) for r in poses]
    report = figures(rig, poses, dots, inlier, floor, table, refined)
    meta = {"source": "calibkit extrinsic --projector", "world_frame": "projector floor"}
    quality = {"extrinsic": {
        "reprojection_rms_px": report["reprojection_rms_px"],
        "mean_ray_distance_mm": report["mean_ray_distance_mm"],
        "mean_ray_distance_table_mm": report["mean_ray_distance_table_mm"],
        "floor_residual_rms_mm": floor.residual_rms_mm}}
    rig = Rig(rig.cameras, quality, {**{k: v for k, v in intrinsics.meta.items()
                                        if k in ("volume_m",)}, **meta})
    report["warnings"] = messages
    return ExtrinsicResult(rig, poses, dots, inlier, refined, report, messages)


def _refigure(res: PoseResult, rig: Rig) -> PoseResult:
    if res.camera is None:
        return res
    return PoseResult(res.name, rig[res.name], res.inlier, res.rms_px, res.floor_dots,
                      res.table_dots, res.warning)


def figures(rig: Rig, poses: list[PoseResult], dots: DotObservations, inlier: np.ndarray,
            floor: PlaneMap, table: PlaneMap | None, xyz: np.ndarray | None = None) -> dict:
    """The report: per camera reprojection RMS (against the dots' positions `xyz`, the
    jointly refined ones when there are, else the plane maps' points), dot counts,
    and the mean ray distance over its dots and over its table dots alone (distance from
    its ray to the dot triangulated by every calibrated camera); overall figures too."""
    sel = dots.select(inlier)
    index = np.array([rig.names.index(n) if n in rig.names else -1 for n in dots.camera_names])
    rows = index[sel.camera] >= 0
    cam, pt, uv = index[sel.camera[rows]], sel.point[rows], sel.uv[rows]
    used, local = np.unique(pt, return_inverse=True)
    tri = triangulate(rig, local, cam, uv, n_points=len(used))
    o, d = RigArrays.from_rig(rig).rays(cam, uv)
    x = tri.xyz[local]
    w = x - o
    ray_to_point = np.linalg.norm(w - np.sum(w * d, axis=1, keepdims=True) * d, axis=1) * 1e3
    on_table = dots.plane[used[local]] == TABLE
    pts_xyz = dots.xyz if xyz is None else np.where(np.isfinite(xyz), xyz, dots.xyz)
    proj, _ = RigArrays.from_rig(rig).project(cam, pts_xyz[pt])
    err = np.sum((proj - uv) ** 2, axis=1)
    per_point = mean_ray_distance(local, o, d, len(used)) * 1000.0
    table_pts = dots.plane[used] == TABLE
    cams = []
    for r in poses:
        k = rig.names.index(r.name) if r.camera is not None else -1
        m = cam == k
        fin = m & np.isfinite(ray_to_point)
        cams.append({
            "name": r.name, "calibrated": r.camera is not None,
            "dots": r.floor_dots + r.table_dots, "floor_dots": r.floor_dots,
            "table_dots": r.table_dots,
            "reprojection_rms_px": float(np.sqrt(np.mean(err[m]))) if m.any() else math.nan,
            "mean_ray_distance_mm": float(np.mean(ray_to_point[fin])) if fin.any()
            else math.nan,
            "mean_ray_distance_table_mm": float(np.mean(ray_to_point[fin & on_table]))
            if (fin & on_table).any() else math.nan,
            "warning": r.warning})

    def nanmean(a):
        a = a[np.isfinite(a)]
        return float(np.mean(a)) if len(a) else math.nan

    return {
        "cameras": cams,
        "calibrated": [r.name for r in poses if r.camera is not None],
        "not_calibrated": [r.name for r in poses if r.camera is None],
        "reprojection_rms_px": float(np.sqrt(np.mean(err))) if len(err) else math.nan,
        "mean_ray_distance_mm": nanmean(per_point),
        "mean_ray_distance_table_mm": nanmean(per_point[table_pts]),
        "mean_ray_distance_floor_mm": nanmean(per_point[~table_pts]),
        "floor_map": {"residual_rms_mm": floor.residual_rms_mm,
                      "residual_max_mm": floor.residual_max_mm, "points": floor.n_points},
        "table_map": None if table is None else {
            "residual_rms_mm": table.residual_rms_mm, "residual_max_mm": table.residual_max_mm,
            "points": table.n_points, "height_m": table.height_m},
        "dots": int(len(used)), "table_dot_points": int(table_pts.sum()),
    }


def floor_recording(rig: Rig, dots: DotObservations, inlier: np.ndarray, n_dots: int = 30,
                    repeats: int = 3):
    """A few well-spread floor dots seen by >= 3 cameras as a recording of static markers:
    `calibkit wand --floor FILE --floor-kind plane` fits the floor plane to them. Sparse, so
    that matching unlabelled blobs across cameras is unambiguous."""
    from calibkit.observations import Observations

    sel = dots.select(inlier)
    floor_rows = dots.plane[sel.point] == FLOOR
    pts, counts = np.unique(sel.point[floor_rows], return_counts=True)
    cand = pts[counts >= 3]
    if len(cand) == 0:
        return None
    xy = dots.xyz[cand, :2]
    chosen = [int(np.argmin(np.linalg.norm(xy - xy.mean(axis=0), axis=1)))]
    dmin = np.linalg.norm(xy - xy[chosen[0]], axis=1)
    while len(chosen) < min(n_dots, len(cand)):
        k = int(np.argmax(dmin))
        chosen.append(k)
        dmin = np.minimum(dmin, np.linalg.norm(xy - xy[k], axis=1))
    keep = np.isin(sel.point, cand[chosen])
    sub = sel.select(keep)
    marker = np.searchsorted(cand[chosen][np.argsort(cand[chosen])], sub.point)
    n = len(sub)
    frame = np.repeat(np.arange(repeats), n)
    sizes = [rig[n].size if n in rig.names else (0, 0) for n in dots.camera_names]
    return Observations(dots.camera_names, sizes, frame, np.tile(sub.camera, repeats),
                        frame * 33_333_333, np.tile(sub.uv, (repeats, 1)),
                        np.full(n * repeats, 20.0), np.full(n * repeats, 200.0),
                        np.tile(marker, repeats), 30.0).sorted()


def save_dots(path: str | Path, dots: DotObservations, inlier: np.ndarray | None = None
              ) -> None:
    """The dots (only the rows in `inlier`) as .npz, atomically: the plane observations a
    wand bundle adjustment can take (load_dots, then bundle_data)."""
    import io

    from calibkit.fileio import write_bytes_atomic

    d = dots if inlier is None else dots.select(inlier)
    buf = io.BytesIO()
    np.savez_compressed(buf, camera_names=np.array(d.camera_names), camera=d.camera,
                        point=d.point, uv=d.uv, xyz=d.xyz, plane=d.plane,
                        plane_height_m=np.array(d.plane_height_m))
    write_bytes_atomic(path, buf.getvalue())


def load_dots(path: str | Path) -> DotObservations:
    path = Path(path)
    try:
        z = np.load(path, allow_pickle=False)
        return DotObservations(tuple(str(n) for n in z["camera_names"]), z["camera"],
                               z["point"], z["uv"], z["xyz"], z["plane"],
                               tuple(float(h) for h in z["plane_height_m"]))
    except FileNotFoundError:
        raise UserError(f"{path}: no such file") from None
    except (OSError, KeyError, ValueError):
        raise UserError(f"{path}: not a dots file written by calibkit extrinsic") from None


def join_bundle_data(a, b):
    """Two calibkit.bundle.BundleData over the same rig as one: b's points are renumbered
    after a's. This is how the projector's dots (bundle_data) join a wand solve: their
    plane and position priors then hold the world frame while the wand refines the rest."""
    from calibkit import bundle

    if a.rig.names != b.rig.names:
        raise ValueError("both BundleData must use the same rig (same cameras, same order)")
    n = len(a.xyz)
    cat = np.concatenate
    return bundle.BundleData(
        a.rig, cat([a.obs_point, b.obs_point + n]), cat([a.obs_camera, b.obs_camera]),
        cat([a.obs_uv, b.obs_uv]), cat([a.xyz, b.xyz]),
        cat([a.edge, b.edge + n]).reshape(-1, 2), cat([a.edge_length_m, b.edge_length_m]),
        cat([a.known_point, b.known_point + n]), cat([a.known_xyz, b.known_xyz]),
        cat([a.plane_point, b.plane_point + n]), cat([a.plane_normal, b.plane_normal]),
        cat([a.plane_offset_m, b.plane_offset_m]))
