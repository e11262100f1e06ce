"""The simulated capture the daemon runs with `--sim`: moving bodies, a person, and cameras
that behave as real ones do.

Each simulated camera opens at its own moment (`[sim] open_spread_s`), counts frames from 0
from its own start, stamps them on its own clock (a random epoch, running fast or slow by
up to `[sim] clock_drift_ppm`), delivers them a transfer delay after it took them (its own
smallest delay plus jitter), and when it reconnects (`drop_camera`) starts again from 0 on
a new epoch. The rig is triggered: every camera takes its frames at the same instants
(plus its fixed `unsync_ms` phase, for free-running cameras). A camera may lose frames
(`lost_frames`): taken and counted, never delivered.

With `[sim.robot]` one more body is a robot driven live (daemon.synthetic.robot): its
blobs are made at each trigger from the commands that have come in, and join the other
bodies' in every camera.

What the capture threads get is what cameras give (blobs, the device's time and frame
counter, the arrival); the truth (bodies' poses, and for every delivered frame which
trigger it was, when it was taken and which marker each blob is) stays in SimScene for the
scorers in daemon.synthetic.evaluator and daemon.synthetic.labelling.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator

import numpy as np

from calibkit.core.camera import Rig
from calibkit.core.errors import UserError
from calibkit.core.observations import Truth
from calibkit.synthetic import person as sim_person
from calibkit.synthetic import sim
from daemon.capture.multiplexer import FrameSet
from daemon.capture.sources import CameraSample, fine_timer_slack
from daemon.config.mocapd import SimConfig
from daemon.synthetic.ledger import Ledger
from daemon.synthetic.robot import LiveRobot

PERSON_MARKER_BASE = 2000  # the simulated person's truth marker ids start here
TRANSFER_NS = (100_000, 500_000)  # range of the cameras' smallest capture-to-arrival delay
JITTER_NS = 50_000  # mean of the exponential delay on top of it
# where a body is held to be defined, as fractions of the volume from its middle at a
# quarter of its size up: the middle first, then a little to a side
HOLD_PLACES = ((0.0, 0.0, 0.0), (0.1, 0.0, 0.0), (0.0, -0.1, 0.02), (-0.08, 0.08, 0.05))
LEDGER = 1 << 15  # delivered frames remembered per camera (136 s at 240 fps)


class SimScene:
    """A simulated capture for the daemon: rig, moving rigid bodies, per-camera blobs, truth.

    `rig` is what the daemon tracks with (a calibrated rig); `truth_rig` is what the blobs
    are made with (the true cameras). The scene is `n_frames` long; longer runs play it
    back and forth (motion stays continuous), `scene_frame(i)` says which frame is shown.
    """

    def __init__(self, cfg: SimConfig, rig: Rig | None = None, truth_rig: Rig | None = None,
                 n_frames: int | None = None, lost_frames: dict[int, float] | None = None
                 ) -> None:
        """`lost_frames`: camera index -> the fraction of its frames taken but never
        delivered (a full bus): its counter and clock run on, the frame is just missing."""
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
        self.t0_ns = 0  # daemon time of trigger 0 (live runs: SimCamera sets it)
        self.first_trigger: dict[int, int] = {}  # camera -> trigger of its first frame
        self.person_labels: list[str] = []
        self.person_xyz = np.zeros((n, 0, 3))  # (frames, 41, 3) the person's markers
        if cfg.person:
            truth = self._add_person(truth, n)
        self.truth = truth
        # free-running cameras: each camera's phase against the trigger, fixed for the run
        self.offsets_ns = np.random.default_rng(cfg.seed + 4).uniform(
            0.0, cfg.unsync_ms * 1e6, len(rig)).round()
        obs = sim.observe(self.truth_rig, truth, noise_px=cfg.noise_px, dropout=cfg.dropout,
                          ghosts_per_camera=cfg.ghosts, fps=cfg.fps, seed=cfg.seed + 3,
                          clock_offset_ns=self.offsets_ns)
        self.obs = obs.sorted()
        self.robot = None
        self._n_scripted = len(self.bodies_truth)  # bodies whose poses are precomputed
        if cfg.robot is not None:
            self._add_robot()
        key = self.obs.frame * len(rig) + self.obs.camera
        self.starts = np.searchsorted(key, np.arange(n * len(rig) + 1))
        # each camera's own start, clock and transfer delay, fixed for the run
        m = len(rig)
        rng = np.random.default_rng(cfg.seed + 5)
        opens = rng.uniform(0.0, 1.0, m)  # the first at once, the last open_spread_s later
        opens = (opens - opens.min()) / max(np.ptp(opens), 1e-9) * cfg.open_spread_s
        self.open_delay_ns = np.round(opens * 1e9).astype(np.int64)
        self.drift_ppm = rng.uniform(-cfg.clock_drift_ppm, cfg.clock_drift_ppm, m)
        self.transfer_ns = rng.uniform(*TRANSFER_NS, m).round().astype(np.int64)
        # the ledger: per camera, by (frame id, device time), what each delivered frame
        # was (trigger, when taken); a reconnected camera reuses frame ids, not times
        self._ledger = Ledger(m, LEDGER)  # compact: a dict of them grew to 76 MB (issue 30)
        self.lost_fraction = np.zeros(m)
        for c, f in (lost_frames or {}).items():
            if not 0 <= f < 1:
                raise UserError(f"a camera's lost-frame fraction must be in [0, 1), got {f}")
            self.lost_fraction[c] = f
        self.lost: list[set] = [set() for _ in range(m)]  # truth: the triggers each lost
        self._poses = None  # (bodies, frames, 4, 4), made when first needed

    def _add_person(self, truth, n: int):
        """A person wearing the 41-marker set walks a circle in the volume (truth marker
        ids PERSON_MARKER_BASE + k, k the index in person_labels)."""
        take = sim_person.walk_circle(n, self.fps, self.cfg.person_radius_m)
        self.person_labels, self.person_xyz = list(take.labels), take.markers_m
        k = len(take.labels)
        return type(truth)(np.concatenate([truth.frame, np.repeat(np.arange(n), k)]),
                           np.concatenate([truth.marker, PERSON_MARKER_BASE
                                           + np.tile(np.arange(k), n)]),
                           np.concatenate([truth.xyz, take.markers_m.reshape(-1, 3)]))

    def _add_robot(self) -> None:
        """The live robot, the last of the scene's bodies (id after the others')."""
        if not self.cfg.realtime:
            raise UserError("[sim.robot] needs the simulation paced in real time (its "
                            "commands come in real time); drop --fast or realtime = false")
        self.robot = LiveRobot(self.cfg, self.truth_rig, self.offsets_ns,
                               len(self.bodies_truth) + 1,
                               [b.markers_body for b in self.bodies_truth])
        self.bodies_truth = [*self.bodies_truth, self.robot.body]

    def close(self) -> None:
        """Stop the live robot (its command socket, the rest of its truth file)."""
        if self.robot is not None:
            self.robot.close()

    def held_alone(self, body: int, n_frames: int, place: int = 0) -> list:
        """Frame sets of the scene's body `body` held still and alone in the volume (the
        others, the person and loose markers set aside), squared with the room's axes, as
        a user holds a body to define it (`mocapd rigid-body add --from-live`): what the
        cameras see of it with this scene's noise, dropouts and stray blobs, a triggered
        rig's frame sets. Only the blobs reach the daemon. `place` picks where it is held
        (HOLD_PLACES, around the middle of the volume): a user whose definition came out
        short of markers moves the body and tries again."""
        cfg, b = self.cfg, self.bodies_truth[body]
        volume = float(self.rig.meta.get("volume_m", cfg.volume_m)) if self.rig.meta \
            else cfg.volume_m
        xyz = b.markers_body + [0.0, 0.0, 0.25 * volume] \
            + np.asarray(HOLD_PLACES[place % len(HOLD_PLACES)]) * volume
        k = len(xyz)
        truth = Truth(np.repeat(np.arange(n_frames), k), np.tile(np.arange(k), n_frames),
                      np.tile(xyz, (n_frames, 1)))
        obs = sim.observe(self.truth_rig, truth, noise_px=cfg.noise_px, dropout=cfg.dropout,
                          ghosts_per_camera=cfg.ghosts, fps=cfg.fps,
                          seed=cfg.seed + 7 + 11 * body + 101 * place).sorted()
        m = len(self.rig)
        starts = np.searchsorted(obs.frame * m + obs.camera, np.arange(n_frames * m + 1))
        sets = []
        for f in range(n_frames):
            t = round(f * 1e9 / cfg.fps)
            samples = [CameraSample(c, f, t, t, obs.uv[s:e], obs.area[s:e], obs.peak[s:e])
                       for c in range(m) for s, e in [(starts[f * m + c],
                                                        starts[f * m + c + 1])]]
            sets.append(FrameSet(f, t, t, samples))
        return sets

    def scene_frame(self, i: int) -> int:
        period = 2 * (self.n_frames - 1)
        k = i % period
        return k if k < self.n_frames else period - k

    def _blobs(self, camera: int, trigger: int, make: bool = True):
        """(uv, area, peak, marker) of camera `camera` at trigger `trigger`; `make`: the
        live robot's blobs are made now if not yet (False: only those made, for scorers;
        None when they were not)."""
        f = self.scene_frame(trigger)
        s, e = self.starts[f * len(self.rig) + camera], self.starts[f * len(self.rig) + camera + 1]
        o = self.obs
        out = o.uv[s:e], o.area[s:e], o.peak[s:e], o.marker[s:e]
        if self.robot is None:
            return out
        live = self.robot.blobs(camera, trigger, self.t0_ns) if make \
            else self.robot.known_blobs(camera, trigger)
        if live is None:
            return None
        return tuple(np.concatenate([a, b]) for a, b in zip(out, live, strict=True))

    def deliver(self, camera: int, trigger: int, frame_id: int, device_ns: int, t_ns: int,
                arrival_ns: int, taken_ns: int) -> CameraSample:
        """What camera `camera` delivers for trigger `trigger`, as its driver would: blobs,
        its frame counter and timestamp; the ledger keeps the truth of it."""
        self._ledger.add(camera, frame_id, device_ns, trigger, taken_ns)
        uv, area, peak, _ = self._blobs(camera, trigger)
        return CameraSample(camera, frame_id, t_ns, arrival_ns, uv, area, peak, device_ns,
                            frame_id)

    def sample(self, camera: int, i: int, t_ns: int) -> CameraSample:
        """Trigger i of a camera that opened with the others at trigger 0 on a perfect
        clock (runs as fast as the tracker goes, which have no capture threads)."""
        taken = round(i * 1e9 / self.fps) + int(self.offsets_ns[camera])
        return self.deliver(camera, i, i, taken, t_ns, time.monotonic_ns(), taken)

    # ---- the truth, for the scorers ------------------------------------------------------

    def _entry(self, sample) -> tuple[int, int] | None:
        """(trigger, taken_ns) of a delivered sample, found by its camera, frame id and
        timestamp; None if the ledger never held it or has forgotten it."""
        return self._ledger.get(sample.camera, sample.device_frame_id, sample.device_time_ns)

    def trigger_of(self, sample) -> int:
        """The trigger (the scene's frame counter) a delivered sample was taken at, or -1."""
        e = self._entry(sample)
        return -1 if e is None else e[0]

    def taken_ns(self, sample) -> int | None:
        """When a delivered sample was really taken (daemon clock), or None."""
        e = self._entry(sample)
        return None if e is None else e[1]

    def markers(self, sample, trigger: int | None = None) -> np.ndarray:
        """The true marker of each of a sample's blobs (-1: a stray blob, or unknown);
        `trigger` if the caller has looked it up already."""
        g = self.trigger_of(sample) if trigger is None else trigger
        got = None if g < 0 else self._blobs(sample.camera, g, make=False)
        if got is None:
            return np.full(len(sample.uv), -1, np.int64)
        marker = got[3]
        if len(marker) != len(sample.uv):
            return np.full(len(sample.uv), -1, np.int64)
        return marker

    def truth_of(self, samples) -> tuple[list, np.ndarray]:
        """For a frame's samples: when each was taken (None if unknown) and the true marker
        of every blob, in the samples' order (one ledger look-up per sample)."""
        entries = [self._entry(s) for s in samples]
        taken = [None if e is None else e[1] for e in entries]
        marker = [self.markers(s, -1 if e is None else e[0])
                  for s, e in zip(samples, entries, strict=True)]
        return taken, (np.concatenate(marker) if marker else np.zeros(0, np.int64))

    def frames_at(self, t_ns: int) -> tuple[int, int, float]:
        """The scene frames around daemon time t_ns and the weight of the second: the scene
        is shown at trigger times from t0_ns, back and forth."""
        at = (t_ns - self.t0_ns) * self.fps * 1e-9
        g, w = round(at), 0.0
        if abs(at - g) > 1e-6:  # between frames (else on one, up to rounding)
            g = int(np.floor(at))
            w = at - g
        if g < 0:
            return 0, 0, 0.0
        return self.scene_frame(g), self.scene_frame(g + 1), w

    def body_poses_at(self, t_ns: int) -> tuple[np.ndarray, np.ndarray]:
        """The bodies' true (R (B, 3, 3), t (B, 3)) at daemon time t_ns: between scene
        frames, positions linearly and rotations as the nearest rotation to the blend of
        the two frames' (its polar factor, by Newton steps: the blend is orthonormal to
        within (turn between frames)^2 / 8, and each step squares that, so two leave none
        the scorer's arccos could see). Within 1e-5 degrees of the geodesic for the degree
        or less a body turns between frames, and cheap on the frame loop, where a
        quaternion slerp or an SVD costs about 100 us a frame."""
        if self._poses is None:
            scripted = self.bodies_truth[:self._n_scripted]
            self._poses = np.stack([b.poses for b in scripted]) \
                if scripted else np.zeros((0, self.n_frames, 4, 4))
        fa, fb, w = self.frames_at(t_ns)
        Ta = self._poses[:, fa]
        if w == 0.0:
            R, t = Ta[:, :3, :3], Ta[:, :3, 3]
        else:
            T = (1 - w) * Ta + w * self._poses[:, fb]
            R, t = T[:, :3, :3], T[:, :3, 3]
            for _ in range(2):
                R = 1.5 * R - 0.5 * R @ np.swapaxes(R, 1, 2) @ R
        if self.robot is None:
            return R, t
        Rr, tr = self.robot.pose_at(t_ns)
        return np.concatenate([R, Rr[None]]), np.concatenate([t, tr[None]])

    def person_at(self, t_ns: int) -> np.ndarray:
        """The person's true markers (41, 3) at daemon time t_ns."""
        fa, fb, w = self.frames_at(t_ns)
        return (1 - w) * self.person_xyz[fa] + w * self.person_xyz[fb]

    def dropped(self, camera: int, i: int) -> bool:
        """True while the configured camera is disconnected (fault injection): from
        drop_from_s after its first frame, so that a camera whose thread opened late (a
        loaded machine) still goes away, for drop_for_s."""
        cfg = self.cfg
        if not cfg.drop_camera or self.rig.names[camera] != cfg.drop_camera:
            return False
        first = self.first_trigger.get(camera)
        if first is None:  # not opened yet
            return False
        t = (i - first) / self.fps
        return cfg.drop_from_s <= t < cfg.drop_from_s + cfg.drop_for_s


class SimCamera:
    """One simulated camera as a capture thread reads it (see the module docstring): its
    first open waits for its own start; every open counts frames from 0 on a new clock
    epoch; frames are taken at the rig's trigger instants and arrive a transfer delay
    later."""

    def __init__(self, scene: SimScene, camera: int, t0_ns: int,
                 now=time.monotonic_ns, sleep=time.sleep) -> None:
        """`now` and `sleep` are the clock it paces itself by: the daemon's, or in tests a
        virtual one (a capture run faster than real time, the same frames and truth)."""
        self.scene, self.camera, self.t0_ns = scene, camera, t0_ns
        scene.t0_ns = t0_ns  # trigger 0: the scorers place frames in time from it
        self.name = scene.rig.names[camera]
        self.sessions = 0
        self.now, self.sleep = now, sleep

    def open(self) -> Iterator[CameraSample]:
        fine_timer_slack()
        now, sleep = self.now, self.sleep
        for due, take in self.session():
            wait = due - now()
            if wait > 0:
                sleep(wait * 1e-9)
            yield take(now())

    def session(self) -> Iterator[tuple[int, Callable[[int], CameraSample]]]:
        """One session's frames as (when it arrives, ns on `now`'s clock; the frame given
        its arrival time), without waiting: open() sleeps between them, and a simulated
        node serves all its cameras from one thread by merging theirs
        (daemon.synthetic.node_sim). Taking a frame while the camera is disconnected
        raises OSError."""
        sc, c = self.scene, self.camera
        period = 1e9 / sc.fps
        session, self.sessions = self.sessions, self.sessions + 1
        rng = np.random.default_rng([sc.cfg.seed, 6, c, session])
        phase = int(sc.offsets_ns[c])  # free-running cameras: a fixed phase
        start = self.now()
        if session == 0:
            start = max(start, self.t0_ns + int(sc.open_delay_ns[c]))
        g = max(0, int(np.ceil((start - self.t0_ns - phase) / period)))
        epoch = int(rng.integers(1, 2**42))  # its clock at its first frame: since power-up
        rate = 1.0 + sc.drift_ppm[c] * 1e-6
        first = self.t0_ns + round(g * period) + phase
        sc.first_trigger.setdefault(c, g)
        k = 0
        # its own stream: a scene that loses no frames draws exactly what it always did
        losing = np.random.default_rng([sc.cfg.seed, 8, c, session]) \
            if sc.lost_fraction[c] > 0 else None
        while True:
            taken = self.t0_ns + round(g * period) + phase
            due = taken + int(sc.transfer_ns[c]) + round(rng.exponential(JITTER_NS))
            device = epoch + round((taken - first) * rate)
            if losing is not None and losing.random() < sc.lost_fraction[c]:
                sc.lost[c].add(g)  # taken, counted, never delivered
                g += 1
                k += 1
                continue

            def take(arrival: int, g=g, k=k, device=device, taken=taken) -> CameraSample:
                if sc.dropped(c, g):
                    raise OSError("camera disconnected (simulated)")
                return sc.deliver(c, g, k, device, arrival, arrival, taken)

            yield due, take
            g += 1
            k += 1
