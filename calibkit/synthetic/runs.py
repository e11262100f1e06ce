"""Setting up a `--sim` run of a calibration command: the simulated hardware, and the checks
that the estimate files given belong to it.

The hardware (a true rig) is seen only by the simulator and the scorers; the estimate
starts from the estimate files the previous step wrote. Command handlers call these.
"""

from __future__ import annotations

from pathlib import Path

from calibkit.core.camera import Rig
from calibkit.core.errors import UserError
from calibkit.synthetic import sim


def truth_rig_path(out: Path) -> Path:
    """Where a simulated run writes the true rig beside its result: NAME.truth.toml."""
    return out.with_name(out.stem + ".truth.toml")


def sim_hardware(sim_rig: Path | None, cameras: int, volume_m: float, seed: int,
                 size: tuple[int, int] = (640, 480)) -> Rig:
    """The simulated hardware a `--sim` run observes: the true rig in `--sim-rig`, else a
    ring of `cameras` cameras made from --volume and --seed (`calibkit sim rig` makes the
    same one). Only the simulator and the truth files see it; the estimate starts from
    estimate files."""
    if sim_rig is not None:
        return Rig.load(sim_rig)
    return sim.make_rig(cameras, volume_m, size, seed=seed)


def check_estimate(estimate: Rig, hardware: Rig, path: Path | None, option: str) -> None:
    """A `--sim` run's estimate file must hold every simulated camera, at its image size:
    a file from another simulated rig would otherwise be calibrated against the wrong
    cameras without a word."""
    where = f"{option} {path}" if path is not None else option
    for cam in hardware:
        if cam.name not in estimate.names:
            raise UserError(f"camera '{cam.name}' of the simulated rig has no intrinsics in "
                            f"{where} (it has {', '.join(estimate.names)}): give every step "
                            "the same --sim-rig (or --cameras, --volume and --seed)")
        if tuple(estimate[cam.name].size) != tuple(cam.size):
            w, h = estimate[cam.name].size
            raise UserError(f"camera '{cam.name}' is {w}x{h} in {where} but "
                            f"{cam.size[0]}x{cam.size[1]} in the simulated rig: give every "
                            "step the same --sim-rig (or --cameras, --volume and --seed)")


def need_intrinsics_for_sim(command: str) -> UserError:
    """The error for a `--sim` run given no estimate to start from: the truth is never it."""
    return UserError(f"{command} --sim starts from estimated intrinsics: run `calibkit "
                     "intrinsic --sim --camera all --rig intrinsics.toml` first (same "
                     "--sim-rig, or --cameras and --seed) and pass --intrinsics "
                     "intrinsics.toml")
