"""`calibkit wand --sim`: a simulated wand dance (and L-frame) seen by the true rig, handed
to the wand pipeline as a live capture's batches of frames would be.

The estimate starts from the estimate file (--intrinsics or --rig) and sees only
unlabelled blobs per camera and frame, as each camera delivers them: its own frame counter
from its own opening, its own stamps (offset, drift, jitter) and its lost frames
(calibkit.synthetic.camclocks), so the capture has to pair frames by time. The true rig is
written to NAME.truth.toml, and which instant each camera frame shows stays in
`WandSimRun.frame_truth`, for the scorers.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from calibkit.calibrate import floor
from calibkit.calibrate.wand_pipeline import World
from calibkit.core.camera import Rig
from calibkit.core.errors import UserError
from calibkit.core.observations import Observations, Truth
from calibkit.synthetic import camclocks, sim
from calibkit.synthetic.runs import check_estimate, need_intrinsics_for_sim, sim_hardware

CHUNK_FRAMES = 50  # simulated frames handed to the capture loop at a time
FPS = 100.0


@dataclass(frozen=True, eq=False)
class WandSimRun:
    """The true rig, the estimate's cameras in the hardware's order (as a live capture's
    --camera order), the dance's observations, and the world frame from an L-frame at the
    true origin (None when the projector's dots hold the frame)."""

    truth: Rig
    intrinsics: Rig
    observations: Observations
    world: World | None
    frame_truth: camclocks.FrameTruth | None = None  # the scorers' only

    def batches(self) -> Iterator[Observations]:
        """The capture as it arrives: CHUNK_FRAMES frame periods of every camera's frames
        at a time, by their stamps."""
        obs = self.observations
        if not len(obs):
            return
        period = 1e9 / (obs.fps or FPS)
        slot = ((obs.t_ns - obs.t_ns.min()) // round(CHUNK_FRAMES * period)).astype(np.int64)
        starts = np.searchsorted(np.sort(slot), np.arange(int(slot.max()) + 2))
        order = np.argsort(slot, kind="stable")
        for lo, hi in zip(starts[:-1], starts[1:], strict=True):
            if hi > lo:
                yield obs.select(order[lo:hi]).sorted()


def lframe_observations(rig: Rig, lframe: floor.LFrame, seed: int,
                        noise_px: float) -> Observations:
    """A simulated L-frame lying on the true floor at the origin, 30 frames."""
    pts = lframe.points((0.0, 0.0), 0.0)
    n = 30
    truth = Truth(np.repeat(np.arange(n), 3), np.tile(np.arange(3), n), np.tile(pts, (n, 1)))
    return sim.observe(rig, truth, noise_px=noise_px, seed=seed + 17)


def setup(estimate: Rig | None, estimate_path: Path | None, option: str,
          sim_rig: Path | None, cameras: int | None, volume_m: float, frames: int,
          spacing_m, noise_px: float, ghosts: float, seed: int, with_lframe: bool,
          clocks: camclocks.CameraClocks | None = None) -> WandSimRun:
    """The hardware (--sim-rig, else the ring `calibkit intrinsic --sim` made with the same
    options, whose image size the estimate file records), a wand dance of `frames` frames
    and, with_lframe, an L-frame at the origin that sets the world frame. `clocks`: the
    cameras' clocks (default: camclocks.make_clocks for the seed: opening within 0.5 s,
    +-1 ms offsets, +-30 ppm, 50 us jitter, no frame lost)."""
    if estimate is None:
        raise need_intrinsics_for_sim("calibkit wand")
    if sim_rig is not None and cameras is not None:
        raise UserError("give --sim-rig or --cameras, not both: the rig file sets the "
                        "cameras")
    true_rig = sim_hardware(sim_rig, cameras or len(estimate), volume_m, seed,
                            estimate.cameras[0].size)
    check_estimate(estimate, true_rig, estimate_path, option)
    intr = Rig(tuple(estimate[n] for n in true_rig.names), estimate.quality, estimate.meta)
    volume_m = float(true_rig.meta.get("volume_m", volume_m))
    truth = sim.wand_motion(frames, FPS, volume_m, spacing_m, seed)
    obs = sim.observe(true_rig, truth, noise_px=noise_px, ghosts_per_camera=ghosts, seed=seed,
                      fps=FPS)
    clocks = clocks or camclocks.make_clocks(len(true_rig), seed)
    obs, frame_truth = camclocks.per_camera(obs, clocks, frames, FPS, seed)
    world = None
    if with_lframe:
        floor_obs = lframe_observations(true_rig, floor.LFrame(), seed, noise_px)

        def world(r, _xyz):  # the L-frame lies at the true origin: truth's frame
            return floor.world_from_recording(r, floor_obs, "lframe")
    return WandSimRun(true_rig, intr, obs, world, frame_truth)
