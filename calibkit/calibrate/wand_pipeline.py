"""The wand calibration from end to end, as `calibkit wand` runs it: capture until every
camera has enough, set up the world frame, solve, write the files.

Each step takes what hardware (or a recording) gives, so the command handler only parses
and prints, and the simulator (calibkit.synthetic.wand_sim) can hand in its batches of
frames and its floor recording without the rest knowing. What hardware gives is each
camera's own frames: its own counter and capture times, frames lost on the way. They are
recorded as they are and grouped into wand frames by capture time before the solve
(calibkit.core.pairing); older recordings that number frames by instant are read as
they are.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import ExitStack
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from calibkit.calibrate import floor, plane_views, wand_report
from calibkit.calibrate.extrinsic_capture import load_dots
from calibkit.calibrate.extrinsic_solve import bundle_data
from calibkit.calibrate.wand import CaptureMonitor, WandSpec, identify
from calibkit.cameras import open_camera
from calibkit.core.camera import Rig
from calibkit.core.errors import UserError
from calibkit.core.observations import Observations
from calibkit.core.pairing import PER_CAMERA, pair_frames
from calibkit.core.recording import RecordingWriter, load_observations
from calibkit.vision.detect import DetectorConfig, detect

World = Callable[[Rig, np.ndarray], tuple[np.ndarray, np.ndarray]]


def capture(batches: Iterator[Observations], spec: WandSpec, intrinsics: Rig,
            monitor: CaptureMonitor, writer: RecordingWriter | None,
            progress) -> Observations | None:
    """Feed batches of frames through identification until every camera has enough (or
    Ctrl-C); every batch is appended to the recording as it comes. Returns what it got, as
    the cameras gave it (not yet paired: pair_frames). progress: has update(frames, text)
    and finish(text) (calibkit.clitools.Progress); frames counts the busiest camera's."""
    parts: list[Observations] = []
    frames = 0
    try:
        for batch in batches:
            if len(batch):
                parts.append(batch)
                monitor.add(identify(batch, spec, intrinsics))
                if writer is not None:
                    writer.append_observations(batch)
            frames += _frames_in(batch)
            progress.update(frames, monitor.summary())
            if monitor.done():
                break
    except KeyboardInterrupt:
        progress.finish("interrupted: using what was captured")
        return Observations.concatenate(parts) if parts else None
    progress.finish(monitor.summary())
    return Observations.concatenate(parts) if parts else None


def _frames_in(batch: Observations) -> int:
    """The frames of the camera that delivered most in a batch (1 for an empty batch)."""
    if not len(batch):
        return 1
    key = np.unique(batch.camera.astype(np.int64) << 40 | (batch.frame & ((1 << 40) - 1)))
    return int(np.bincount((key >> 40).astype(np.int64)).max())


def live_batches(specs: list[str], rig: Rig) -> Iterator[Observations]:
    """One frame from every camera at a time, detected: cameras (calibkit.cameras specs) named
    as in the rig, in the order given. Each row keeps its camera's own frame number (the
    device's frame counter where it gives one, else the source's count) and capture time:
    a camera that lost a frame is a frame ahead of the others from then on, which only the
    times tell (pair_frames)."""
    if len(specs) != len(rig):
        raise UserError(f"give one --camera per camera of the intrinsics file ({len(rig)}), "
                        f"got {len(specs)}")
    config = DetectorConfig()
    with ExitStack() as opened:  # a camera that fails to open closes those opened before it
        sources = [opened.enter_context(open_camera(s, name=n))
                   for s, n in zip(specs, rig.names, strict=True)]
        for frames in zip(*sources, strict=False):
            rows = []
            for c, frame in enumerate(frames):
                blobs = detect(frame.image, config)
                n = len(blobs.uv)
                own = frame.device_frame_id if frame.device_frame_id >= 0 else frame.index
                rows.append(Observations(rig.names, [cam.size for cam in rig],
                                         np.full(n, own), np.full(n, c),
                                         np.full(n, frame.t_ns), blobs.uv, blobs.area,
                                         blobs.peak, meta={"frames": PER_CAMERA}))
            yield Observations.concatenate(rows)


@dataclass(frozen=True)
class CaptureTargets:
    """When a capture has enough: wand sightings and share of image cells per camera."""

    min_samples: int = 1000
    min_coverage: float = 0.8

    def __post_init__(self) -> None:
        if self.min_samples < 1 or not 0 <= self.min_coverage <= 1:
            raise UserError("--min-samples must be >= 1 and --min-coverage in [0, 1]")


def record_capture(batches: Iterator[Observations], spec: WandSpec, intrinsics: Rig,
                   targets: CaptureTargets, path: Path, fps: float | None, progress,
                   monitor: CaptureMonitor | None = None
                   ) -> tuple[Observations, CaptureMonitor]:
    """Capture into a recording at `path` (fps: the camera rate, if known) until every
    camera has enough; the observations paired into wand frames (pair_frames) and the
    monitor with its coverage figures (the one given, e.g. one a page shows as it fills,
    or a new one for `targets`). The recording keeps each camera's own frames and times
    (its header says so), so reading it back pairs them the same way."""
    monitor = monitor or new_monitor(intrinsics, targets)
    with RecordingWriter(path, intrinsics.names, [c.size for c in intrinsics], fps,
                         meta={"frames": PER_CAMERA}) as writer:
        obs = capture(batches, spec, intrinsics, monitor, writer, progress)
    if obs is None:
        raise UserError("nothing was captured")
    obs.fps = obs.fps or fps
    obs.meta = {**obs.meta, "frames": PER_CAMERA}
    return pair_frames(obs).obs, monitor


def load_capture(path: Path, intrinsics: Rig) -> Observations:
    """A recorded capture (--from: .mcrec or CSV) with its frames paired into wand frames:
    by capture time when each camera counts its own, as recorded when frames already
    name instants (pairing.frames_are_instants)."""
    obs, _ = load_observations(path, intrinsics)
    return pair_frames(obs).obs


def new_monitor(intrinsics: Rig, targets: CaptureTargets) -> CaptureMonitor:
    return CaptureMonitor(intrinsics.names, [c.size for c in intrinsics],
                          targets.min_samples, targets.min_coverage)


def world_from_floor(path: Path, intrinsics: Rig, kind: str, spec: WandSpec) -> World:
    """The world frame from a recording of the L-frame, the wand or plane dots on the
    floor (--floor, --floor-kind)."""
    obs = load_capture(path, intrinsics)

    def world(rig: Rig, _xyz: np.ndarray):
        return floor.world_from_recording(rig, obs, kind, spacing_m=spec.spacing_m)

    return world


def dots_extra(path: Path):
    """The projector's floor and table dots (NAME.dots.npz from calibkit extrinsic) as
    extra bundle rows, held on their planes only: their positions come from a homography
    fitted to tape measurements (mm errors) and priors on them pull the wand's scale and
    shape; the planes alone kept the rig 2.7x closer to the truth (docs/wand.md)."""
    dots = load_dots(path)

    def extra(start_rig: Rig):
        return bundle_data(start_rig, dots, known=False)

    return extra


def monitor_views(intrinsics: Rig, intrinsics_path: Path | None):
    """The intrinsic step's monitor views its rig file names (None without)."""
    return plane_views.load_for(intrinsics.quality, intrinsics_path, intrinsics.names)


def write_outputs(cal, out: Path, plots: bool) -> None:
    """The rig file and, with plots, NAME.layout.png and NAME.residuals.png."""
    cal.rig.save(out)
    if plots:
        wand_report.plot_layout(cal.rig, cal.solved["xyz"],
                                out.with_name(out.stem + ".layout.png"))
        wand_report.plot_residuals(cal.rig, cal.solved,
                                   out.with_name(out.stem + ".residuals.png"))
