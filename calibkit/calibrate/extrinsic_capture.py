"""Capturing the projector's coded dots with every camera of a rig at once, and the dots
they yield as multi-camera observations of points on known planes.

The projector shows a coded schedule (projector.patterns); each camera settles on its own
(latencies differ per camera), and the dots are found and named exactly as the
single-camera monitor capture does (calibkit.calibrate.dotcapture: one DotFilter, one
naming). Hardware enters through `ProjectorRig` (show dots, grab one frame per camera):
a live projector window with the rig's cameras (`LiveProjectorRig`, the display made by
the command), or the simulator. Nothing here draws: the display is given.
"""

from __future__ import annotations

import io
import math
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import numpy as np

from calibkit.calibrate.dotcapture import DOT_FILTER, DotFilter, NamedDots, identify_dots
from calibkit.calibrate.extrinsic_reference import PlaneMap, dot_world_points
from calibkit.calibrate.settle import SettleDetector, signature_noise
from calibkit.core.errors import UserError
from calibkit.core.fileio import write_bytes_atomic
from calibkit.vision.gray import to_gray
from projector.dots import Dots
from projector.patterns import Schedule


class DotDisplay(Protocol):
    """A projector window (or anything that shows dots)."""

    def show(self, dots: Dots) -> None: ...


class ProjectorRig(Protocol):
    """What capture needs from hardware: the projector shows dots, every camera delivers
    its next frame (one image per camera, in rig order)."""

    def show(self, dots: Dots) -> None: ...

    def grab(self) -> list[np.ndarray]: ...


class LiveProjectorRig:
    """A projector display and the rig's frame sources (one per camera, in rig order) as
    one ProjectorRig. The caller opens and closes both."""

    def __init__(self, display: DotDisplay, sources: Iterable, names: list[str]) -> None:
        self.display = display
        self.iters = [iter(s) for s in sources]
        self.names = list(names)

    def show(self, dots: Dots) -> None:
        self.display.show(dots)

    def grab(self) -> list[np.ndarray]:
        out = []
        for name, it in zip(self.names, self.iters, strict=True):
            frame = next(it, None)
            if frame is None:
                raise UserError(f"camera {name} stopped delivering frames")
            out.append(frame.image)
        return out


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


def _camera_dots(named: NamedDots) -> CameraDots:
    return CameraDots(named.ids, named.uv, named.scatter_px, named.rejected)


@dataclass(frozen=True, eq=False)
class SessionCapture:
    """A session's dots per camera, the camera frames it took and each camera's latency
    (frames from a pattern change to the first changed image; None if never seen)."""

    cameras: list[CameraDots]
    frames: int
    latency_frames: list[int | None]


def capture_session(device: ProjectorRig, schedule: Schedule, n_cameras: int,
                    samples: int = 3, hold: int = 1, max_settle_frames: int = 60,
                    dot_filter: DotFilter = DOT_FILTER, progress=None,
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
    The dots are found and named as the single-camera capture does (dotcapture).
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
                    shots[c].append(to_gray(images[c], np.float32))
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
                        shots[c] = [to_gray(images[c], np.float32)] * samples
                break
        for c in range(n_cameras):
            if len(shots[c]) >= samples:
                step_images[c][i] = np.mean(shots[c][:samples], axis=0)
                on_shots[c][i] = shots[c][:samples]
            else:
                step_images[c][i] = None
        if progress is not None:
            progress(i + 1, len(schedule.frames))
    cams = [_camera_dots(identify_dots(schedule, step_images[c], on_shots[c], dot_filter))
            for c in range(n_cameras)]
    return SessionCapture(cams, frames, [d.latency_frames for d in settle])


def _latency_passed(own: int | None, known: list[int], first: bool, waited: int,
                    hold: int) -> bool:
    """Has a camera whose image did not change waited past its latency (its own, else the
    slowest known; never on the first pattern when it has none)?"""
    if own is None and (first or not known):
        return False
    return waited > (own if own is not None else max(known)) + hold + 2


def capture_frames_estimate(schedule: Schedule, latency_frames: list[int], samples: int = 3,
                            hold: int = 1) -> int:
    """Camera frames a session takes when the slowest camera settles `max(latency) + hold`
    frames after each change (what capture_session does, without images)."""
    per = max(latency_frames) + hold + samples
    return 8 + len(schedule.frames) * per


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


def save_dots(path: str | Path, dots: DotObservations, inlier: np.ndarray | None = None
              ) -> None:
    """The dots (only the rows in `inlier`) as .npz, atomically: the plane observations a
    wand bundle adjustment can take (load_dots, then bundle_data)."""
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
