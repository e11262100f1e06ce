"""`calibkit wand --sim`: a simulated wand dance (and L-frame) seen by the true rig, handed
to the wand pipeline as a live capture's batches of frames would be.

The estimate starts from the estimate file (--intrinsics or --rig) and sees only
unlabelled blobs per camera and frame; the true rig is written to NAME.truth.toml for the
scorers.
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
from calibkit.synthetic import sim
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

    def batches(self) -> Iterator[Observations]:
        obs = self.observations
        frames = obs.frames()
        for i in range(0, len(frames), CHUNK_FRAMES):
            lo, hi = frames[i], frames[min(i + CHUNK_FRAMES, len(frames)) - 1]
            yield obs.select((obs.frame >= lo) & (obs.frame <= hi))


def lframe_observations(rig: Rig, lframe: floor.LFrame, seed: int,
                        noise_px: float) -> Observations:
    """A simulated L-frame lying on the true floor at the origin, 30 frames."""
    pts = lframe.points((0.0, 0.0), 0.0)
    n = 30
    truth = Truth(np.repeat(np.arange(n), 3), np.tile(np.arange(3), n), np.tile(pts, (n, 1)))
    return sim.observe(rig, truth, noise_px=noise_px, seed=seed + 17)


def setup(estimate: Rig | None, estimate_path: Path | None, option: str,
          sim_rig: Path | None, cameras: int | None, volume_m: float, frames: int,
          spacing_m, noise_px: float, ghosts: float, seed: int, with_lframe: bool
          ) -> WandSimRun:
    """The hardware (--sim-rig, else the ring `calibkit intrinsic --sim` made with the same
    options, whose image size the estimate file records), a wand dance of `frames` frames
    and, with_lframe, an L-frame at the origin that sets the world frame."""
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
    obs = sim.observe(true_rig, truth, noise_px=noise_px, ghosts_per_camera=ghosts, seed=seed)
    world = None
    if with_lframe:
        floor_obs = lframe_observations(true_rig, floor.LFrame(), seed, noise_px)

        def world(r, _xyz):  # the L-frame lies at the true origin: truth's frame
            return floor.world_from_recording(r, floor_obs, "lframe")
    return WandSimRun(true_rig, intr, obs, world)
