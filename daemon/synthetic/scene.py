"""The simulated capture the daemon runs with `--sim`: moving bodies, a person, and cameras
that deliver their blobs at the pace real ones would.

What the capture threads get is what cameras give (blobs and capture times); the truth
(bodies' poses, each blob's marker) stays in SimScene for the scorers in
daemon.synthetic.evaluator.
"""

from __future__ import annotations

import time
from collections.abc import Iterator

import numpy as np

from calibkit.camera import Rig
from calibkit.errors import UserError
from calibkit.synthetic import sim
from daemon.config import SimConfig
from daemon.rigid import BodyDef
from daemon.sources import CameraSample, fine_timer_slack

PERSON_MARKER_BASE = 2000  # the simulated person's truth marker ids start here


class SimScene:
    """A simulated capture for the daemon: rig, moving rigid bodies, per-camera blobs, truth.

    `rig` is what the daemon tracks with (a calibrated rig); `truth_rig` is what the blobs
    are made with (the true cameras). The scene is `n_frames` long; longer runs play it
    back and forth (motion stays continuous), `scene_frame(i)` says which frame is shown.
    """

    def __init__(self, cfg: SimConfig, rig: Rig | None = None, truth_rig: Rig | None = None,
                 n_frames: int | None = None) -> None:
        self.cfg = cfg
        if rig is None:
            rig = sim.make_rig(cfg.cameras, cfg.volume_m, size=cfg.size, seed=cfg.seed)
        self.rig = rig
        self.truth_rig = truth_rig or rig
        if self.truth_rig.names != rig.names:
            raise UserError("the true rig and the tracking rig have different cameras")
        volume = float(rig.meta.get("volume_m", cfg.volume_m)) if rig.meta else cfg.volume_m
        self.fps = cfg.fps
        n = int(n_frames or round(20 * cfg.fps))
        n = max(2, min(n, int(60 * cfg.fps)))
        self.n_frames = n
        truth, self.bodies_truth = sim.rigid_body_motion(
            max(cfg.bodies, 1), n, cfg.fps, volume, cfg.markers_per_body, seed=cfg.seed + 1)
        if cfg.bodies == 0:
            truth, self.bodies_truth = sim._frames_truth(np.zeros((n, 0, 3))), []
        if cfg.extra_markers:
            loose = sim.static_markers(cfg.extra_markers, n, volume, seed=cfg.seed + 2)
            truth = type(truth)(np.concatenate([truth.frame, loose.frame]),
                                np.concatenate([truth.marker, loose.marker + 1000]),
                                np.concatenate([truth.xyz, loose.xyz]))
        self.t0_ns: int | None = None  # live runs: when frame 0 was due (SimCamera sets it)
        self.person_labels: list[str] = []
        self.person_xyz = np.zeros((n, 0, 3))  # (frames, 41, 3) the person's markers
        if cfg.person:
            truth = self._add_person(truth, n)
        self.truth = truth
        # unsynchronised cameras: each camera's clock offset, fixed for the run
        self.offsets_ns = np.random.default_rng(cfg.seed + 4).uniform(
            0.0, cfg.unsync_ms * 1e6, len(rig)).round()
        obs = sim.observe(self.truth_rig, truth, noise_px=cfg.noise_px, dropout=cfg.dropout,
                          ghosts_per_camera=cfg.ghosts, fps=cfg.fps, seed=cfg.seed + 3,
                          clock_offset_ns=self.offsets_ns)
        self.obs = obs.sorted()
        key = self.obs.frame * len(rig) + self.obs.camera
        self.starts = np.searchsorted(key, np.arange(n * len(rig) + 1))

    def _add_person(self, truth, n: int):
        """A person wearing the 41-marker set walks a circle in the volume (truth marker
        ids PERSON_MARKER_BASE + k, k the index in person_labels)."""
        from calibkit.synthetic import person as sim_person

        take = sim_person.walk_circle(n, self.fps, self.cfg.person_radius_m)
        self.person_labels, self.person_xyz = list(take.labels), take.markers_m
        k = len(take.labels)
        return type(truth)(np.concatenate([truth.frame, np.repeat(np.arange(n), k)]),
                           np.concatenate([truth.marker, PERSON_MARKER_BASE
                                           + np.tile(np.arange(k), n)]),
                           np.concatenate([truth.xyz, take.markers_m.reshape(-1, 3)]))

    def body_defs(self) -> list[BodyDef]:
        """The scene's bodies as the daemon would have them defined."""
        return [BodyDef(b.name, b.id, b.markers_body, np.zeros(3)) for b in self.bodies_truth]

    def scene_frame(self, i: int) -> int:
        period = 2 * (self.n_frames - 1)
        k = i % period
        return k if k < self.n_frames else period - k

    def blobs(self, camera: int, i: int):
        """(uv, area, peak, marker) of camera `camera` at daemon frame i."""
        f = self.scene_frame(i)
        s, e = self.starts[f * len(self.rig) + camera], self.starts[f * len(self.rig) + camera + 1]
        o = self.obs
        return o.uv[s:e], o.area[s:e], o.peak[s:e], o.marker[s:e]

    def sample(self, camera: int, i: int, t_ns: int) -> CameraSample:
        uv, area, peak, marker = self.blobs(camera, i)
        return CameraSample(camera, i, t_ns, time.monotonic_ns(), uv, area, peak, marker,
                            self.scene_frame(i))

    def dropped(self, camera: int, i: int) -> bool:
        """True while the configured camera is disconnected (fault injection)."""
        cfg = self.cfg
        if not cfg.drop_camera or self.rig.names[camera] != cfg.drop_camera:
            return False
        t = i / self.fps
        return cfg.drop_from_s <= t < cfg.drop_from_s + cfg.drop_for_s


class SimCamera:
    """One simulated (or replayed) camera as a capture thread reads it: paced at the
    scene's rate from a shared start time, so all cameras' frame i share one capture time
    (a triggered rig). A replay ends with its recording."""

    def __init__(self, scene: SimScene, camera: int, t0_ns: int) -> None:
        self.scene, self.camera, self.t0_ns = scene, camera, t0_ns
        scene.t0_ns = t0_ns  # when frame 0 was due: the Evaluator places frames in time
        self.name = scene.rig.names[camera]

    def open(self) -> Iterator[CameraSample]:
        fine_timer_slack()
        period = 1e9 / self.scene.fps
        i = max(0, int(np.ceil((time.monotonic_ns() - self.t0_ns) / period)))
        end = getattr(self.scene, "frame_numbers", None)
        offsets = getattr(self.scene, "offsets_ns", None)  # unsynchronised simulated clocks
        t0 = self.t0_ns + (int(offsets[self.camera]) if offsets is not None else 0)
        while end is None or i < len(end):
            due = t0 + round(i * period)
            wait = due - time.monotonic_ns()
            if wait > 0:
                time.sleep(wait * 1e-9)
            if self.scene.dropped(self.camera, i):
                raise OSError("camera disconnected (simulated)")
            yield self.scene.sample(self.camera, i, due)
            i += 1
