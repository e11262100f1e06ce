"""Gates that follow the rig: correspondence, triangulation and tracking gates from the
calibration's measured residual, read from the rig file or estimated from the data.

Why: a gate in fixed pixels is right for one rig only. The defaults (2 px from an epipolar
line, 1.5 px of reprojection) suit a rig calibrated to about 0.1-0.4 px; a rig whose
calibration leaves 1 px (webcams, a rolling shutter, an imported calibration) would see
its true matches cut off and most markers lost. So every gate is

    gate = max(default, k * residual_px)

where `residual_px` is the rig's reprojection residual, defined as the calibrations compute
it: the RMS over observations of the distance (px) between a blob and the reprojection of
the point triangulated from all of that point's blobs. `k` is the quantile of the residual's
distribution that keeps all but P_REJECT = 0.1 % of true observations (docs/triangulation.md):

- a single observation's reprojection error after triangulation is a 2D error; with the
  per-axis sigma s = residual / sqrt(2), |e|^2 / s^2 follows a chi-square law with 2
  degrees of freedom, whose 1 - p quantile is -2 ln p, so
  K_REPROJ = sqrt(-2 ln p) / sqrt(2) = 2.63;
- an epipolar distance is 1D, but carries both blobs' errors: its own across the line,
  and the other blob's carried over with a gain g (the ratio of the two depths, up to about
  2 in a room-sized rig), sigma_epi = s sqrt(1 + g^2) <= s sqrt(5); with the two-sided
  normal quantile z(1 - p/2) = 3.29, K_EPIPOLAR = 3.29 sqrt(5) / sqrt(2) = 5.20;
- a point from two cameras splits its epipolar distance between its two images, so its
  RMS reprojection error is about half of it: K_TWO_VIEW = K_EPIPOLAR / 2.

The defaults stay the floor, so a well calibrated rig keeps exactly its old gates.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from calibkit.core.camera import Rig
from calibkit.core.errors import UserError
from calibkit.core.geometry import RigArrays
from calibkit.core.observations import Observations
from calibkit.vision.correspondence import CorrespondenceConfig, match_frames

P_REJECT = 1e-3  # share of true observations a gate may cut off
K_REPROJ = math.sqrt(-2.0 * math.log(P_REJECT)) / math.sqrt(2.0)
K_EPIPOLAR = 3.2905267314919255 * math.sqrt(5.0) / math.sqrt(2.0)  # z(1 - p/2) = 3.29
K_TWO_VIEW = K_EPIPOLAR / 2.0

# the wand solve's residuals in [quality]: on the frames solved and on those held out
_WAND_KEYS = ("held_out_rms_px", "reprojection_rms_px")


@dataclass(frozen=True)
class Residual:
    """The residual the gates follow, and where it came from (said in every output)."""

    px: float
    source: str  # "rig file", "estimated from data", "command line"
    detail: str  # which key of the rig file, or how many points of which frames

    def as_dict(self) -> dict:
        return {"px": self.px, "source": self.source, "detail": self.detail}

    def __str__(self) -> str:
        return f"{self.px:.3f} px ({self.source}: {self.detail})"


def scaled(default_px: float, k: float, residual_px: float | None) -> float:
    """max(default, k * residual): a gate never narrower than its default."""
    if residual_px is None or not np.isfinite(residual_px):
        return float(default_px)
    return float(max(default_px, k * residual_px))


def _figure(value, key: str) -> float | None:
    """A residual from the rig file: None when absent or NaN (a calibration that could not
    measure it), a UserError when it is not a non-negative number."""
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise UserError(f"quality.{key} must be a number of pixels, got {value!r}")
    if math.isnan(value):
        return None
    if value < 0 or math.isinf(value):
        raise UserError(f"quality.{key} must be a non-negative number of pixels, got {value}")
    return float(value)


def rig_residual(rig: Rig) -> Residual | None:
    """The residual recorded in the rig file's [quality], or None if it holds none.

    The wand solve's figures first (the larger of the fit's and the held-out frames', as
    new data behaves like held-out data), then the projector extrinsics', then, where the
    file holds only intrinsics, the RMS over cameras of the intrinsic fits: that one leaves
    the poses' error out and is a lower bound, which the defaults' floor makes safe.
    """
    q = rig.quality or {}
    found = [(k, _figure(q.get(k), k)) for k in _WAND_KEYS]
    found = [(k, v) for k, v in found if v is not None]
    if found:
        key, value = max(found, key=lambda kv: kv[1])
        return Residual(value, "rig file", f"quality.{key}")
    extrinsic = q.get("extrinsic")
    if isinstance(extrinsic, dict):
        value = _figure(extrinsic.get("reprojection_rms_px"), "extrinsic.reprojection_rms_px")
        if value is not None:
            return Residual(value, "rig file", "quality.extrinsic.reprojection_rms_px")
    intrinsic = q.get("intrinsic")
    if isinstance(intrinsic, dict):
        sq, n = 0.0, 0.0
        for name, fig in intrinsic.items():
            if not isinstance(fig, dict):
                continue
            value = _figure(fig.get("rms_px"), f"intrinsic.{name}.rms_px")
            if value is None:
                continue
            points = fig.get("points", 1)
            w = float(points) if isinstance(points, (int, float)) and points > 0 else 1.0
            sq += w * value * value
            n += w
        if n:
            return Residual(math.sqrt(sq / n), "rig file",
                            "quality.intrinsic.*.rms_px (intrinsics only: a lower bound)")
    return None


def rig_residual_px(rig: Rig) -> float | None:
    """The residual (px) the rig file records, or None."""
    found = rig_residual(rig)
    return None if found is None else found.px


def correspondence_config(residual_px: float | None,
                          base: CorrespondenceConfig | None = None,
                          fixed: frozenset[str] | set[str] = frozenset()) -> CorrespondenceConfig:
    """`base` with its pixel gates scaled from the residual, except those named in `fixed`
    (set by the user)."""
    base = base or CorrespondenceConfig()
    changes = {}
    if "epipolar_px" not in fixed:
        changes["epipolar_px"] = scaled(base.epipolar_px, K_EPIPOLAR, residual_px)
    if "max_reproj_px" not in fixed:
        changes["max_reproj_px"] = scaled(base.max_reproj_px, K_REPROJ, residual_px)
    return replace(base, **changes)


def tracker_gates(residual_px: float | None, defaults: dict[str, float],
                  fixed: frozenset[str] | set[str] = frozenset()) -> dict[str, float]:
    """The tracker's pixel gates from the residual, for the names in `defaults` that are not
    `fixed`: gate_px (a blob from a track's reprojection) and outlier_px (an observation's
    residual) are single-observation errors (K_REPROJ); two_view_px a two-camera point's
    RMS (K_TWO_VIEW); ambiguous_px, the margin by which a track's nearest blob must beat
    the next candidate, is a difference of two such distances, whose spread is the
    residual itself, so K_REPROJ of it too. Unknown names are left out."""
    k = {"gate_px": K_REPROJ, "outlier_px": K_REPROJ, "two_view_px": K_TWO_VIEW,
         "ambiguous_px": K_REPROJ}
    return {name: scaled(value, k[name], residual_px) for name, value in defaults.items()
            if name in k and name not in fixed}


# ---- the residual measured on the data itself ---------------------------------------------

WIDE_EPIPOLAR_PX = 8.0  # the first pass's gates: wide enough for a few pixels of residual
WIDE_REPROJ_PX = 6.0
MIN_POINTS = 20  # fewer confident points than this give no estimate
# The later passes measure through a reprojection gate this many times the one their figure
# sets. A gate of K_REPROJ x residual censors the blobs that would raise the figure: a normal
# error loses 0.1 % to it, but a real rig's residual has a tail (4 webcams: 99th percentile at
# 3.0 x RMS, a normal error's at 2.15 x), so each pass cuts off more of it and the figure
# settles low (0.59 px against 0.84 px measured with the corners' ids: docs/triangulation.md).
# At 2 x the censoring starts at 5.3 x RMS (webcams: 0.74 px). The price is the chance blobs
# the wider gate lets in on crowded rigs: simulated ones (50 markers, stray blobs) read 2-6 %
# high at 1 px, up to 18 % at 2 px with 8 cameras. The epipolar gate stays at K_EPIPOLAR x:
# it is what keeps chance matches out (widened as well, 1 px rigs read 5-10 % high) and
# widening it moved the webcams' figure by 1 %.
MEASURE_REPROJ_WIDEN = 2.0


def _robust_rms(error_px: np.ndarray) -> float:
    """RMS of 2D errors from their median: for a 2D normal error |e|^2 / s^2 is chi-square
    with 2 degrees of freedom (median 2 ln 2, mean 2), so RMS = median|e| / sqrt(ln 2).
    A few wrong blobs among the matches barely move the median."""
    return float(np.median(error_px) / math.sqrt(math.log(2.0)))


def point_residuals(rig: Rig, obs: Observations, rows: np.ndarray,
                    xyz: np.ndarray) -> np.ndarray:
    """Each used blob's reprojection error (px) against its point: rows (P, C) of `obs`."""
    index = {name: i for i, name in enumerate(rig.names)}
    cam_map = np.array([index[n] for n in obs.camera_names], dtype=np.int64)
    point, slot = np.nonzero(rows >= 0)
    blob = rows[point, slot]
    proj, _ = RigArrays.from_rig(rig).project(cam_map[obs.camera[blob]], xyz[point])
    return np.linalg.norm(proj - obs.uv[blob], axis=1)


def estimate_residual(rig: Rig, obs: Observations, max_blobs: int = 3000,
                      max_frames: int = 200, rounds: int = 4,
                      reproj_widen: float = MEASURE_REPROJ_WIDEN) -> Residual | None:
    """The rig's residual measured on the data's confident matches, or None if too few.

    On the first frames (up to `max_blobs` blobs, a few hundred markers, and at most
    `max_frames` frames; at least one frame): markers matched by >= 3 cameras (a pair is never
    trusted: two rays always meet), and the RMS of their blobs' reprojection errors. The
    first pass has wide gates, so chance matches are among its points: it takes the robust
    RMS (from the median). Each later pass matches with the epipolar gate the previous
    figure gives (K_EPIPOLAR x residual, without the defaults' floor), which keeps out
    chance matches, and a reprojection gate `reproj_widen` times the one it gives, so that
    the tail the figure must size is not cut away (MEASURE_REPROJ_WIDEN; 1 is the estimate
    before issue 28), and takes the plain RMS: the median-based figure assumes a 2D normal
    error, and a rig's systematic residual is not quite one (measured: 10-17 % low on a
    simulated four-camera rig, 30 % low on four real webcams).
    """
    frames, per_frame = np.unique(obs.frame, return_counts=True)
    frames = frames[:max(1, min(max_frames, int(np.searchsorted(np.cumsum(per_frame),
                                                                 max_blobs, side="right"))))]
    sub = obs.select(np.isin(obs.frame, frames))
    cfg = CorrespondenceConfig(epipolar_px=WIDE_EPIPOLAR_PX, max_reproj_px=WIDE_REPROJ_PX,
                               min_cameras=3, two_camera=False)
    residual, n_points = None, 0
    for k in range(rounds):
        points = match_frames(rig, sub, cfg)
        three = points.n_cameras >= 3
        n_points = int(three.sum())
        if n_points < MIN_POINTS:
            return None
        error = point_residuals(rig, sub, points.rows[three], points.xyz[three])
        residual = _robust_rms(error) if k == 0 else float(np.sqrt(np.mean(error**2)))
        # the gates this residual gives, without the defaults' floor: on a rig far better
        # than the defaults assume, a 2 px gate would let chance blobs into the figure
        cfg = CorrespondenceConfig(epipolar_px=K_EPIPOLAR * residual,
                                   max_reproj_px=reproj_widen * K_REPROJ * residual,
                                   min_cameras=3, two_camera=False)
    return Residual(residual, "estimated from data",
                    f"{n_points} points seen by >= 3 cameras in the first {len(frames)} frames")


def choose_residual(rig: Rig, obs: Observations | None = None,
                    residual_px: float | None = None, estimate: bool = False
                    ) -> Residual | None:
    """The residual a command's gates follow: the user's figure, else the rig file's (unless
    `estimate`), else one measured on `obs`; None when there is none (the defaults hold)."""
    if residual_px is not None:
        if not np.isfinite(residual_px) or residual_px < 0:
            raise UserError(f"--residual-px must be a non-negative number, got {residual_px}")
        return Residual(float(residual_px), "command line", "--residual-px")
    if not estimate:
        found = rig_residual(rig)
        if found is not None:
            return found
    if obs is None:
        return None
    return estimate_residual(rig, obs)


def gated_config(rig: Rig, obs: Observations | None = None, residual_px: float | None = None,
                 estimate: bool = False, base: CorrespondenceConfig | None = None,
                 fixed: frozenset[str] | set[str] = frozenset()
                 ) -> tuple[CorrespondenceConfig, Residual | None]:
    """The correspondence configuration `calibkit triangulate` runs with, and the residual
    its gates follow (None: the defaults hold). Gates named in `fixed` keep `base`'s value;
    when both are fixed nothing is measured."""
    base = base or CorrespondenceConfig()
    if {"epipolar_px", "max_reproj_px"} <= set(fixed):
        return base, None
    residual = choose_residual(rig, obs, residual_px, estimate)
    return correspondence_config(None if residual is None else residual.px, base, fixed), \
        residual
