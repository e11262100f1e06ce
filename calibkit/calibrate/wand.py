"""Wand capture: find the wand's markers in every camera and frame, track capture coverage,
and compute initial camera poses from nothing (essential matrix, then PnP, wand-length scale).

Identification works per (frame, camera) on the blobs alone, before any pose is known, so
it must be robust by itself: a 3-marker wand is the one collinear triple whose spacing
ratio fits (the unequal spacings tell its ends apart); a group with two fitting triples is
ambiguous and dropped rather than guessed. Everything is vectorised over groups: groups of
the same blob count are stacked and all their triples tested at once.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field

import cv2
import numpy as np

from calibkit.core.camera import Camera, Rig
from calibkit.core.errors import UserError
from calibkit.core.geometry import RigArrays, triangulate
from calibkit.core.observations import Observations

MAX_BLOBS = 8  # groups with more blobs than this are too cluttered to identify a wand in


@dataclass(frozen=True)
class WandSpec:
    """Marker positions along the rod, metres from marker 0 (e.g. (0, 0.2, 0.5))."""

    spacing_m: tuple[float, ...]

    def __post_init__(self) -> None:
        s = tuple(float(v) for v in self.spacing_m)
        if not 1 <= len(s) <= 3:
            raise UserError(f"a wand has 1, 2 or 3 markers, got spacing {list(s)}")
        if any(b <= a for a, b in zip(s, s[1:], strict=False)):
            raise UserError(f"wand spacing must increase along the rod, got {list(s)}")
        if len(s) == 3 and abs((s[1] - s[0]) - (s[2] - s[1])) < 0.1 * (s[2] - s[0]):
            raise UserError("a 3-marker wand needs unequal spacings (e.g. 0,0.2,0.5) so that "
                            "its ends can be told apart")
        object.__setattr__(self, "spacing_m", s)

    @property
    def n_markers(self) -> int:
        return len(self.spacing_m)

    @property
    def length_m(self) -> float:
        return self.spacing_m[-1] - self.spacing_m[0]

    @property
    def ratio(self) -> float:
        """Where the middle marker sits along the rod, as a fraction of its length."""
        s = self.spacing_m
        return (s[1] - s[0]) / (s[2] - s[0])

    def edges(self) -> tuple[np.ndarray, np.ndarray]:
        """Marker pairs (E, 2) and their true distances (E,) in metres."""
        pairs = np.array(list(itertools.combinations(range(self.n_markers), 2)), dtype=np.int64)
        pairs = pairs.reshape(-1, 2)
        s = np.asarray(self.spacing_m)
        return pairs, s[pairs[:, 1]] - s[pairs[:, 0]]


@dataclass(eq=False)
class WandObservations:
    """Identified wand markers: one row per (frame, camera, marker)."""

    camera_names: tuple[str, ...]
    camera_sizes: tuple[tuple[int, int], ...]
    frame: np.ndarray  # int64 (N,)
    camera: np.ndarray  # int32 (N,)
    marker: np.ndarray  # int32 (N,) 0..k-1 along the wand
    uv: np.ndarray  # float64 (N, 2) distorted pixels as observed
    stats: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.frame)

    def select(self, mask) -> WandObservations:
        return WandObservations(self.camera_names, self.camera_sizes, self.frame[mask],
                                self.camera[mask], self.marker[mask], self.uv[mask],
                                dict(self.stats))

    def frames(self) -> np.ndarray:
        return np.unique(self.frame)


def _undistorted_px(rig: Rig, camera: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Pixels with the lens distortion removed (straight lines stay straight)."""
    arrays = RigArrays.from_rig(rig)
    n = arrays.undistort(camera, uv)
    return np.stack([arrays.fx[camera] * n[:, 0] + arrays.skew[camera] * n[:, 1]
                     + arrays.cx[camera], arrays.fy[camera] * n[:, 1] + arrays.cy[camera]],
                    axis=1)


def _fit_triples(p: np.ndarray, ratio: float, ratio_tol: float, line_tol_px: float,
                 min_length_px: float) -> tuple[np.ndarray, np.ndarray]:
    """For triples p (..., 3, 2): whether each is the wand, and the order (..., 3) that puts
    the blobs in marker order 0, 1, 2."""
    # order the three along their longest side: the two far-apart blobs are the ends
    d01 = np.linalg.norm(p[..., 0, :] - p[..., 1, :], axis=-1)
    d02 = np.linalg.norm(p[..., 0, :] - p[..., 2, :], axis=-1)
    d12 = np.linalg.norm(p[..., 1, :] - p[..., 2, :], axis=-1)
    sides = np.stack([d12, d02, d01], axis=-1)  # side opposite blob i
    middle = np.argmax(sides, axis=-1)  # the blob facing the longest side
    ends = np.stack([(middle + 1) % 3, (middle + 2) % 3], axis=-1)
    take = np.take_along_axis
    a = take(p, ends[..., 0, None, None], axis=-2)[..., 0, :]
    b = take(p, ends[..., 1, None, None], axis=-2)[..., 0, :]
    m = take(p, middle[..., None, None], axis=-2)[..., 0, :]
    ab = b - a
    length = np.linalg.norm(ab, axis=-1)
    safe = np.maximum(length, 1e-9)
    along = np.sum((m - a) * ab, axis=-1) / safe
    off = np.abs(ab[..., 0] * (m - a)[..., 1] - ab[..., 1] * (m - a)[..., 0]) / safe
    r = along / safe
    fits_fwd = np.abs(r - ratio) <= ratio_tol
    fits_rev = np.abs((1.0 - r) - ratio) <= ratio_tol
    ok = (off <= line_tol_px) & (length >= min_length_px) & (fits_fwd != fits_rev)
    first = np.where(fits_fwd, ends[..., 0], ends[..., 1])
    last = np.where(fits_fwd, ends[..., 1], ends[..., 0])
    return ok, np.stack([first, middle, last], axis=-1)


def identify(obs: Observations, spec: WandSpec, intrinsics: Rig | None = None,
             ratio_tol: float = 0.07, line_tol_px: float = 2.0,
             min_length_px: float = 8.0) -> WandObservations:
    """The wand's markers in every (frame, camera) where they can be told apart for sure.

    3 markers: the one collinear triple (middle blob within line_tol_px of the line through
    the ends, after undistortion when intrinsics are given) whose middle sits at the wand's
    spacing ratio within ratio_tol; perspective bends the ratio when the wand points at the
    camera, so those views are dropped. A group with two fitting triples is ambiguous (a
    stray blob lines up) and dropped. 2 markers: groups of exactly two blobs, ordered
    left-to-right (their identity across cameras is settled later, with the poses). 1
    marker: groups of exactly one blob.
    """
    k = spec.n_markers
    names, sizes = obs.camera_names, obs.camera_sizes
    order = np.lexsort((obs.camera, obs.frame))
    frame, camera, uv = obs.frame[order], obs.camera[order], obs.uv[order]
    key = frame * (len(names) + 1) + camera
    starts = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
    counts = np.diff(np.r_[starts, len(key)])
    pix = _undistorted_px(intrinsics, camera, uv) if intrinsics is not None else uv
    rows: list[np.ndarray] = []
    labels: list[np.ndarray] = []
    ambiguous = np.zeros(len(names), dtype=np.int64)
    if k == 1:
        g = starts[counts == 1]
        rows.append(g)
        labels.append(np.zeros(len(g), dtype=np.int32))
    elif k == 2:
        g = starts[counts == 2]
        left_first = uv[g, 0] <= uv[g + 1, 0]
        rows.append(np.concatenate([g, g + 1]))
        labels.append(np.concatenate([np.where(left_first, 0, 1), np.where(left_first, 1, 0)])
                      .astype(np.int32))
    else:
        for n in range(3, MAX_BLOBS + 1):
            g = starts[counts == n]
            if len(g) == 0:
                continue
            combos = np.array(list(itertools.combinations(range(n), 3)))  # (T, 3)
            idx = g[:, None, None] + combos[None]  # (G, T, 3)
            ok, orders = _fit_triples(pix[idx], spec.ratio, ratio_tol, line_tol_px,
                                      min_length_px)
            n_fit = ok.sum(axis=1)
            single = n_fit == 1
            np.add.at(ambiguous, camera[g[n_fit > 1]], 1)
            which = np.argmax(ok, axis=1)[single]
            sel_idx = idx[single][np.arange(single.sum()), which]  # (S, 3) blob rows
            sel_ord = orders[single][np.arange(single.sum()), which]  # (S, 3) positions
            chosen = np.take_along_axis(sel_idx, sel_ord, axis=1)  # rows in marker order
            rows.append(chosen.reshape(-1))
            labels.append(np.tile(np.arange(3, dtype=np.int32), len(chosen)))
    r = np.concatenate(rows) if rows else np.zeros(0, dtype=np.int64)
    lab = np.concatenate(labels) if labels else np.zeros(0, dtype=np.int32)
    wand = WandObservations(names, sizes, frame[r], camera[r], lab, uv[r])
    wand = wand.select(np.lexsort((wand.marker, wand.camera, wand.frame)))
    per_cam = np.bincount(wand.camera[wand.marker == 0], minlength=len(names))
    seen = np.bincount(camera[starts], minlength=len(names))
    wand.stats = {"frames_with_wand": per_cam.tolist(), "frames_with_blobs": seen.tolist(),
                  "ambiguous": ambiguous.tolist()}
    return wand


# ---- capture progress ------------------------------------------------------------------------

class CaptureMonitor:
    """Samples and image coverage per camera while the wand is waved; says when to stop.

    A camera has enough when it holds `min_samples` wand sightings and its image grid
    (`grid` cells across, rows in proportion) has `min_coverage` of its cells visited:
    a calibration is only as good as the part of the image the wand went through.
    """

    def __init__(self, camera_names, camera_sizes, min_samples: int = 1000,
                 min_coverage: float = 0.8, grid: int = 8) -> None:
        self.names = tuple(camera_names)
        self.sizes = np.array(camera_sizes, dtype=np.float64).reshape(-1, 2)
        self.min_samples, self.min_coverage = int(min_samples), float(min_coverage)
        self.gx = int(grid)
        self.gy = max(1, int(round(grid * np.median(self.sizes[:, 1] / self.sizes[:, 0]))))
        self.samples = np.zeros(len(self.names), dtype=np.int64)
        self.cells = np.zeros((len(self.names), self.gy, self.gx), dtype=bool)

    def add(self, wand: WandObservations) -> None:
        first = wand.marker == 0
        self.samples += np.bincount(wand.camera[first], minlength=len(self.names))
        c = wand.camera
        ix = np.clip((wand.uv[:, 0] / self.sizes[c, 0] * self.gx).astype(int), 0, self.gx - 1)
        iy = np.clip((wand.uv[:, 1] / self.sizes[c, 1] * self.gy).astype(int), 0, self.gy - 1)
        self.cells[c, iy, ix] = True

    @property
    def coverage(self) -> np.ndarray:
        return self.cells.reshape(len(self.names), -1).mean(axis=1)

    def camera_done(self) -> np.ndarray:
        return (self.samples >= self.min_samples) & (self.coverage >= self.min_coverage)

    def done(self) -> bool:
        return bool(np.all(self.camera_done()))

    def summary(self) -> str:
        return " ".join(f"{n}:{s}/{100 * c:.0f}%" for n, s, c in
                        zip(self.names, self.samples, self.coverage, strict=True))

    def grid_text(self) -> str:
        """The cells each camera's markers visited ('#') and not ('.'), cameras side by
        side: where in the image to wave the wand next."""
        width = max(self.gx, max(len(n) for n in self.names))
        lines = ["  ".join(n.ljust(width) for n in self.names)]
        for y in range(self.gy):
            lines.append("  ".join("".join("#" if v else "." for v in self.cells[c, y])
                                   .ljust(width) for c in range(len(self.names))))
        return "\n".join(line.rstrip() for line in lines)

    def rows(self) -> list[list]:
        return [[n, int(s), round(100 * float(c), 1), "yes" if d else "no"]
                for n, s, c, d in zip(self.names, self.samples, self.coverage,
                                      self.camera_done(), strict=True)]


# ---- initial poses from nothing ---------------------------------------------------------------

def point_index(wand: WandObservations, n_markers: int) -> tuple[np.ndarray, np.ndarray]:
    """Each row's 3D point number, and the (frame, marker) of each point."""
    key = wand.frame * n_markers + wand.marker
    uniq, inv = np.unique(key, return_inverse=True)
    return inv.astype(np.int64), np.stack([uniq // n_markers, uniq % n_markers], axis=1)


def _normalised(intrinsics: Rig, wand: WandObservations) -> np.ndarray:
    return RigArrays.from_rig(intrinsics).undistort(wand.camera.astype(np.int64), wand.uv)


def _pair_counts(wand: WandObservations, n_cams: int) -> np.ndarray:
    """Shared wand markers per camera pair (C, C)."""
    frames = np.unique(wand.frame)
    seen = np.zeros((len(frames), n_cams), dtype=np.float64)
    seen[np.searchsorted(frames, wand.frame), wand.camera] = 1.0
    return seen.T @ seen


def _relative_pose(n_a: np.ndarray, n_b: np.ndarray, threshold: float):
    """Pose of camera b relative to a (x_b = R x_a + t, |t| = 1) from normalised points."""
    E, inliers = cv2.findEssentialMat(n_a, n_b, np.eye(3), method=cv2.RANSAC, prob=0.9999,
                                      threshold=threshold)
    if E is None or E.shape != (3, 3):
        raise UserError("the wand views of the first camera pair give no essential matrix: "
                        "wave the wand through more of the volume")
    _, R, t, mask = cv2.recoverPose(E, n_a, n_b, np.eye(3), mask=inliers)
    return R, t.ravel(), mask.ravel() > 0


def _with_pose(cam: Camera, R: np.ndarray, t: np.ndarray) -> Camera:
    return cam.replace(R=R, t=np.asarray(t, dtype=np.float64))


def initial_poses(wand: WandObservations, intrinsics: Rig, spec: WandSpec,
                  min_points: int = 12, candidates: int = 4,
                  unscaled: bool = False) -> tuple[Rig, list[str]]:
    """Poses for every camera that sees enough of the wand, from nothing.

    A well-connected pair gives a relative pose from its essential matrix; the wand's
    length scales it; the other cameras are added one by one by PnP on the markers already
    triangulated, most-connected first. Some pairs give a poor essential matrix (little
    parallax, a near-critical configuration), so the `candidates` best-connected pairs are
    each grown into a whole rig and the one whose markers reproject best is kept. The
    frame is the first camera of the pair's. Returns the rig of the cameras placed and the
    names of those that could not be. `unscaled`: a 1-marker spec is accepted and the
    baseline of the first pair is 1 (the caller scales the rig).
    """
    if spec.n_markers < 2 and not unscaled:
        raise UserError("a 1-marker wand gives no scale: give --rig with initial poses")
    n_cams = len(intrinsics)
    counts = _pair_counts(wand, n_cams)
    np.fill_diagonal(counts, 0)
    if counts.max() < min_points:
        raise UserError("no two cameras see the wand together often enough to start; "
                        "wave it where at least two cameras see it")
    norm = _normalised(intrinsics, wand)
    pidx, pinfo = point_index(wand, spec.n_markers)
    iu = np.triu_indices(n_cams, 1)
    order = np.argsort(-counts[iu], kind="stable")[:candidates]
    best = None
    for k in order:
        a, b = int(iu[0][k]), int(iu[1][k])
        if counts[a, b] < min_points:
            continue
        try:
            placed, missing = _grow(wand, intrinsics, spec, a, b, norm, pidx, pinfo,
                                    min_points)
        except UserError:
            continue
        score = (len(missing), _median_reprojection(wand, placed, pidx, len(pinfo)))
        if best is None or score < best[0]:
            best = (score, placed, missing)
    if best is None:
        raise UserError("no camera pair gives a relative pose from the wand: wave it through "
                        "more of the volume")
    return best[1], best[2]


def _median_reprojection(wand: WandObservations, placed: Rig, pidx: np.ndarray,
                         n_points: int) -> float:
    names = {n: i for i, n in enumerate(placed.names)}
    local = np.array([names.get(n, -1) for n in wand.camera_names])
    use = local[wand.camera] >= 0
    tri = triangulate(placed, pidx[use], local[wand.camera[use]], wand.uv[use],
                      n_points=n_points, ray_distance=False)
    ok = np.isfinite(tri.reproj_px)
    return float(np.median(tri.reproj_px[ok])) if ok.any() else float("inf")


def _grow(wand, intrinsics, spec, a, b, norm, pidx, pinfo, min_points):
    """A rig grown from the pair (a, b): essential matrix, scale, then PnP for the rest."""
    n_cams = len(intrinsics)
    n_points = len(pinfo)
    in_a = np.full(n_points, -1)
    in_b = np.full(n_points, -1)
    in_a[pidx[wand.camera == a]] = np.flatnonzero(wand.camera == a)
    in_b[pidx[wand.camera == b]] = np.flatnonzero(wand.camera == b)
    both = np.flatnonzero((in_a >= 0) & (in_b >= 0))
    f = float(np.mean([intrinsics[a].fx, intrinsics[b].fx]))
    R, t, inl = _relative_pose(norm[in_a[both]], norm[in_b[both]], threshold=1.0 / f)
    cams: dict[int, Camera] = {a: _with_pose(intrinsics[a], np.eye(3), np.zeros(3)),
                               b: _with_pose(intrinsics[b], R, t)}
    # scale from the wand's length
    xyz = _triangulate_placed(wand, cams, pidx, n_points)
    scale = _scale_from_length(xyz, pinfo, spec) if spec.n_markers > 1 else 1.0
    cams[b] = _with_pose(intrinsics[b], R, t * scale)
    missing: list[str] = []
    while len(cams) + len(missing) < n_cams:
        xyz = _triangulate_placed(wand, cams, pidx, n_points)
        known = np.isfinite(xyz[:, 0])
        best, best_n = -1, 0
        for c in range(n_cams):
            if c in cams or intrinsics[c].name in missing:
                continue
            n_c = int(np.sum(known[pidx[wand.camera == c]]))
            if n_c > best_n:
                best, best_n = c, n_c
        if best < 0 or best_n < min_points:
            missing += [intrinsics[c].name for c in range(n_cams)
                        if c not in cams and intrinsics[c].name not in missing]
            break
        rows = np.flatnonzero((wand.camera == best) & known[pidx])
        ok, rvec, tvec, _ = cv2.solvePnPRansac(xyz[pidx[rows]], norm[rows], np.eye(3), None,
                                               reprojectionError=2.0 / intrinsics[best].fx,
                                               iterationsCount=200,
                                               flags=cv2.SOLVEPNP_EPNP)
        if not ok:
            missing.append(intrinsics[best].name)
            continue
        rvec, tvec = cv2.solvePnPRefineLM(xyz[pidx[rows]], norm[rows], np.eye(3), None,
                                          rvec, tvec)
        cams[best] = intrinsics[best].replace(rvec=rvec.ravel(), t=tvec.ravel())
    # two cheap passes of "triangulate with everyone, re-solve each camera by PnP" spread
    # the first pair's errors over all cameras before the bundle adjustment
    for _ in range(2):
        xyz = _triangulate_placed(wand, cams, pidx, n_points)
        known = np.isfinite(xyz[:, 0])
        for c in list(cams):
            rows = np.flatnonzero((wand.camera == c) & known[pidx])
            if len(rows) < min_points:
                continue
            rvec, tvec = cv2.solvePnPRefineLM(xyz[pidx[rows]], norm[rows], np.eye(3), None,
                                              cams[c].rvec.copy(), cams[c].t.copy())
            cams[c] = cams[c].replace(rvec=rvec.ravel(), t=tvec.ravel())
        scale = _scale_from_length(_triangulate_placed(wand, cams, pidx, n_points), pinfo,
                                   spec) if spec.n_markers > 1 else 1.0
        cams = {c: cam.replace(t=cam.t * scale) for c, cam in cams.items()}
    placed = Rig(tuple(cams[c] for c in sorted(cams)), meta=dict(intrinsics.meta))
    return placed, missing


def _triangulate_placed(wand: WandObservations, cams: dict[int, Camera], pidx: np.ndarray,
                        n_points: int) -> np.ndarray:
    order = sorted(cams)
    rig = Rig(tuple(cams[c] for c in order))
    local = np.full(max(cams) + 1 if cams else 0, -1)
    local[order] = np.arange(len(order))
    cam_local = local[np.minimum(wand.camera, len(local) - 1)]
    use = (wand.camera < len(local)) & (cam_local >= 0)
    tri = triangulate(rig, pidx[use], cam_local[use], wand.uv[use], iterations=2,
                      n_points=n_points, ray_distance=False)
    return tri.xyz


def _scale_from_length(xyz: np.ndarray, pinfo: np.ndarray, spec: WandSpec) -> float:
    """Metres per unit of the reconstruction: the wand's true length over its median length."""
    lengths = wand_lengths(xyz, pinfo, spec)
    lengths = lengths[np.isfinite(lengths)]
    if len(lengths) < 5:
        raise UserError("too few wand frames seen by the first camera pair to find the scale")
    return spec.length_m / float(np.median(lengths))


def wand_lengths(xyz: np.ndarray, pinfo: np.ndarray, spec: WandSpec) -> np.ndarray:
    """End-to-end wand length of every frame whose two end markers are both reconstructed
    (NaN where not), one value per frame that has marker 0."""
    last = spec.n_markers - 1
    key = pinfo[:, 0] * spec.n_markers + pinfo[:, 1]
    first = np.flatnonzero(pinfo[:, 1] == 0)
    want = pinfo[first, 0] * spec.n_markers + last
    pos = np.searchsorted(key, want)
    pos = np.minimum(pos, len(key) - 1)
    found = key[pos] == want
    out = np.full(len(first), np.nan)
    out[found] = np.linalg.norm(xyz[first[found]] - xyz[pos[found]], axis=1)
    return out
