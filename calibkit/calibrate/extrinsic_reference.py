"""Reference points, plane maps and world points of the projector extrinsic calibration.

All cameras see the same projected dot at the same moment, so once we know where a
projector pixel lands in the world, each dot is a known world point for every camera that
sees it. Where a pixel lands comes from a few reference dots the user measures with a
tape: a homography projector -> floor (and one projector -> table top, at the table's
measured height). Floor points alone fix a camera well near the floor but poorly above it
(a small tilt error grows with height); the table's plane, 0.75 m up, pins the cameras at
head height too. This module reads and checks the tape measurements, fits the maps and
says which projector dots land where; capture (extrinsic_capture), the pose solve
(extrinsic_solve) and the figures (extrinsic_report) build on it.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from calibkit.core.errors import UserError
from projector.patterns import ROLE_BIT, ROLE_OFF, ROLE_ON, PatternFrame, Schedule, code_bits

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib  # type: ignore[no-redef]

FLOOR, TABLE = 0, 1
MIN_REFERENCES = 4


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


@dataclass(frozen=True, eq=False)
class PlaneMap:
    """Projector pixels -> a horizontal plane at height_m: homography H (3x3); the fit's RMS
    and largest residual at the reference points (mm; 0 with exactly 4 points, which fit any
    homography exactly and so check nothing); the plane's outline (K, 2) for the table; and
    the reference points' spread (root-sum-square distance from their middle, metres),
    which with the tape's error says how well the map knows the plane's scale."""

    H: np.ndarray
    height_m: float
    residual_rms_mm: float
    residual_max_mm: float
    n_points: int
    outline_xy_m: np.ndarray | None = None
    spread_m: float = float("nan")

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
    spread = float(np.sqrt(np.sum((xy - xy.mean(axis=0)) ** 2)))
    return PlaneMap(H, float(height_m), float(np.sqrt(np.mean(r**2))), float(r.max()), len(px),
                    spread_m=spread)


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
    return floor, dataclasses.replace(table, outline_xy_m=hull)


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
