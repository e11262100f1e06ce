"""Running the daemon in the foreground as `mocapd start` does: what its options change in
the configuration, and a run until stopped or for a number of frames or seconds.

The command parses; this applies and runs, so an option added to `mocapd start` is one
field here and one line there.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

from calibkit.core.camera import Rig
from calibkit.core.errors import UserError
from daemon.config.mocapd import Config, ReplayIn, SimConfig
from daemon.service.console import Progress

# --realtime without a [pipeline] realtime_priority: above ordinary work and interrupt
# threads' defaults (50) stay ahead of it
REALTIME_DEFAULT = 10


@dataclass(frozen=True)
class StartOverrides:
    """What `mocapd start`'s options change in the configuration (applied again after a
    reload, so a SIGHUP keeps them)."""

    rig: Path | None = None
    runtime_dir: Path | None = None
    mode: str | None = None
    replay: Path | None = None
    fast: bool = False
    sim: bool = False
    sim_bodies: int | None = None
    sim_cameras: int | None = None
    sim_fps: float | None = None
    noise_px: float | None = None
    seed: int | None = None
    realtime: bool = False  # --realtime: SCHED_RR at the file's priority, else REALTIME_DEFAULT

    def apply(self, cfg: Config) -> Config:
        changes = {}
        if self.rig is not None:
            changes["rig"] = self.rig
        if self.runtime_dir is not None:
            changes["runtime_dir"] = self.runtime_dir
        if self.mode is not None:
            changes["mode"] = self.mode
        if self.realtime and cfg.realtime_priority == 0:
            changes["realtime_priority"] = REALTIME_DEFAULT
        if self.replay is not None:
            changes["replay"] = ReplayIn(self.replay, realtime=not self.fast)
        elif self.fast and cfg.replay is not None:
            changes["replay"] = replace(cfg.replay, realtime=False)
        if self.sim or cfg.sim is not None:
            s = cfg.sim or SimConfig()
            sim_changes = {"realtime": not self.fast} if self.fast else {}
            for key, value in (("bodies", self.sim_bodies), ("cameras", self.sim_cameras),
                               ("fps", self.sim_fps), ("noise_px", self.noise_px),
                               ("seed", self.seed)):
                if value is not None:
                    sim_changes[key] = value
            s = replace(s, **sim_changes)
            changes["sim"] = s
            changes["fps"] = s.fps
        return replace(cfg, **changes)


def run_daemon(cfg: Config, reload_config, truth_rig: Path | None, frames: int | None,
               duration: float | None, view: str | None = None) -> dict:
    """Run the daemon on `cfg` until stopped (SIGTERM) or for `frames` / `duration`, with
    progress when either is given; `reload_config` rebuilds the configuration on SIGHUP;
    `view` ("HOST:PORT") serves the live web view. Returns its figures."""
    # deferred on purpose: loads OpenCV, SciPy's sparse graphs... only where used
    from daemon.service.daemon import Daemon

    if cfg.sim is not None and cfg.sim.fps <= 0:
        raise UserError(f"--sim-fps must be positive, got {cfg.sim.fps}")
    truth = Rig.load(truth_rig) if truth_rig is not None else None
    daemon = Daemon(cfg, truth, extend=reload_config)
    if view is not None:
        # the view's server starts now, loading while the daemon sets up; deferred so a
        # daemon without --view never imports the web stack
        from calibkit.clitools import parse_view
        from daemon.view.link import ViewLink

        daemon.view = ViewLink(*parse_view(view))
    daemon.install_signals()
    fps = cfg.sim.fps if cfg.sim else cfg.fps
    total = frames or (int(duration * fps) if duration else None)
    progress = Progress("mocapd", total) if total else None
    figures = daemon.run(frames, duration, progress.update if progress else None)
    if progress:
        progress.finish()
    return figures
