"""Daemon-side blob sources: what each capture thread reads, and the simulator's truth.

A blob source yields CameraSample (one camera's blobs of one frame). Real cameras are
frame sources (calibkit.sources) followed by detection; the simulator yields blobs directly
(rendering 8 images at 240 fps would measure the renderer, not the tracker), with the
true marker of each blob so tracking can be scored. Industrial cameras come from optional
plugins; a plugin whose library is missing is reported and skipped.
"""

from __future__ import annotations

import importlib.util
import logging
import time
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from calibkit import sim
from calibkit.camera import Rig
from calibkit.errors import UserError
from daemon.config import SimConfig
from daemon.rigid import BodyDef, matrix_from_quaternion

log = logging.getLogger("mocapd.sources")

PLUGINS = {"basler": "pypylon", "genicam": "harvesters"}
PERSON_MARKER_BASE = 2000  # the simulated person's truth marker ids start here


@dataclass(eq=False)
class CameraSample:
    """One camera's blobs of one frame."""

    camera: int
    index: int  # frame number (the same number across cameras when they are triggered)
    t_ns: int  # capture time (monotonic ns)
    arrival_ns: int  # when the daemon got it
    uv: np.ndarray  # (N, 2) distorted pixels
    area: np.ndarray  # (N,)
    peak: np.ndarray  # (N,)
    marker: np.ndarray | None = None  # (N,) true marker ids (simulator only)
    scene_frame: int = -1  # the simulator's frame (truth index)


def missing_plugins(kinds) -> list[str]:
    """The camera plugins asked for whose library is not installed."""
    return [f"{k} (needs {PLUGINS[k]})" for k in kinds
            if k in PLUGINS and importlib.util.find_spec(PLUGINS[k]) is None]


# ---- the simulator -------------------------------------------------------------------------

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
        from calibkit import sim_person

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


class ReplayScene:
    """A recording (.mcrec or CSV) played back to the daemon, camera by camera.

    The recording's cameras are matched to the rig's by name; frames are taken in order
    at the recording's frame rate (or as fast as the tracker goes)."""

    def __init__(self, path, rig: Rig) -> None:
        from calibkit.recording import load_observations

        obs, _ = load_observations(path)
        index = {n: i for i, n in enumerate(rig.names)}
        unknown = [n for n in obs.camera_names if n not in index]
        if unknown:
            raise UserError(f"{path}: cameras {', '.join(unknown)} are not in the rig "
                            f"({', '.join(rig.names)})")
        self.rig = rig
        self.fps = float(obs.fps or 100.0)
        cam = np.array([index[n] for n in obs.camera_names])[obs.camera]
        self.frame_numbers = np.unique(obs.frame)
        self.n_frames = len(self.frame_numbers)
        if self.n_frames == 0:
            raise UserError(f"{path}: the recording has no frames")
        order = np.lexsort((cam, np.searchsorted(self.frame_numbers, obs.frame)))
        self.obs, self.cam = obs.select(order), cam[order]
        key = np.searchsorted(self.frame_numbers, self.obs.frame) * len(rig) + self.cam
        self.starts = np.searchsorted(key, np.arange(self.n_frames * len(rig) + 1))

    def sample(self, camera: int, i: int, t_ns: int) -> CameraSample:
        k = i * len(self.rig) + camera
        s, e = self.starts[k], self.starts[k + 1]
        o = self.obs
        return CameraSample(camera, i, t_ns, time.monotonic_ns(), o.uv[s:e], o.area[s:e],
                            o.peak[s:e], None if o.marker is None else o.marker[s:e])

    def dropped(self, camera: int, i: int) -> bool:
        return False


def fine_timer_slack() -> None:
    """Let this thread's sleeps end on time (Linux lets a sleep overrun by the thread's
    timer slack, 50 us by default, to batch wake-ups); a simulated camera that wakes late
    would add that to every frame's latency. Best effort: elsewhere it does nothing."""
    try:
        import ctypes

        ctypes.CDLL(None).prctl(29, 1, 0, 0, 0)  # PR_SET_TIMERSLACK: 1 ns
    except (OSError, AttributeError):
        pass


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


class DetectCamera:
    """A real camera: a calibkit frame source, detection, and undistortion left to the
    tracker (it works in distorted pixels)."""

    def __init__(self, name: str, camera: int, spec: str, detector=None, fps: float = 30.0):
        self.name, self.camera, self.spec, self.fps = name, camera, spec, fps
        self.detector = detector

    def open(self) -> Iterator[CameraSample]:
        from calibkit.detect import DetectorConfig, detect

        source = open_camera(self.spec, self.fps)
        cfg = self.detector or DetectorConfig()
        try:
            for frame in source:
                arrival = time.monotonic_ns()
                blobs = detect(frame.image, cfg)
                yield CameraSample(self.camera, frame.index, frame.t_ns, arrival, blobs.uv,
                                   blobs.area, blobs.peak)
        finally:
            source.close()


def open_camera(spec: str, fps: float):
    """A calibkit frame source for a camera spec; industrial cameras through their plugins."""
    from calibkit.sources import open_source

    kind, _, serial = spec.partition(":")
    if kind == "basler":
        return _PylonSource(serial)
    if kind == "genicam":
        return _HarvesterSource(serial)
    return open_source(spec, fps=fps)


class _PylonSource:
    """A Basler camera through pypylon (untested here: no camera on the build machine)."""

    def __init__(self, serial: str) -> None:
        from pypylon import pylon

        factory = pylon.TlFactory.GetInstance()
        devices = [d for d in factory.EnumerateDevices()
                   if not serial or d.GetSerialNumber() == serial]
        if not devices:
            raise OSError(f"no Basler camera {serial or ''} found")
        self.cam = pylon.InstantCamera(factory.CreateDevice(devices[0]))
        self.cam.Open()
        self.cam.StartGrabbing(pylon.GrabStrategy_LatestImageOnly)
        self.pylon = pylon

    def __iter__(self):
        from calibkit.sources import Frame

        i = 0
        while self.cam.IsGrabbing():
            res = self.cam.RetrieveResult(2000, self.pylon.TimeoutHandling_ThrowException)
            try:
                if res.GrabSucceeded():
                    yield Frame(str(self.cam.GetDeviceInfo().GetSerialNumber()), i,
                                time.monotonic_ns(), res.Array.copy())
                    i += 1
            finally:
                res.Release()

    def close(self) -> None:
        self.cam.Close()


class _HarvesterSource:
    """A GenICam camera through harvesters (untested here: no camera on the build machine).
    MOCAPD_GENTL_CTI names the GenTL producer (.cti) file."""

    def __init__(self, serial: str) -> None:
        import os

        from harvesters.core import Harvester

        self.h = Harvester()
        cti = os.environ.get("MOCAPD_GENTL_CTI")
        if not cti:
            raise OSError("set MOCAPD_GENTL_CTI to your camera's GenTL producer (.cti) file")
        self.h.add_file(cti)
        self.h.update()
        sel = {"serial_number": serial} if serial else 0
        self.ia = self.h.create(sel)
        self.ia.start()

    def __iter__(self):
        from calibkit.sources import Frame

        i = 0
        while True:
            with self.ia.fetch(timeout=2.0) as buf:
                comp = buf.payload.components[0]
                image = comp.data.reshape(comp.height, comp.width).copy()
            yield Frame("genicam", i, time.monotonic_ns(), image)
            i += 1

    def close(self) -> None:
        self.ia.stop()
        self.ia.destroy()
        self.h.reset()


# ---- scoring against the truth --------------------------------------------------------------

class Evaluator:
    """Pose errors of the daemon's rigid bodies against the simulator, and identity swaps.

    A track's identity is the true marker most of its blobs came from this frame; a track
    swap is a track whose identity changes. A body swap is a valid body holding a track of
    another marker than its own (checked when the daemon's bodies are the scene's, marker
    for marker: `slots=True`). Poses more than 2 cm or 5 degrees off are counted apart as
    gross errors (a body posed from three close markers seen by few cameras can be that
    far off without any swap); they are left out of the RMS figures and reported.

    It runs on the frame loop, so it is vectorised over the bodies and keeps running sums
    only: its time is added to every frame's (a per-body loop here cost 1.2 ms a frame,
    more than the tracker, and delayed the next frame's pickup).
    """

    def __init__(self, scene: SimScene, skip_frames: int = 5, slots: bool = True) -> None:
        self.scene = scene
        self.skip = skip_frames
        self.slots = slots
        truth = scene.bodies_truth
        nb = len(truth)
        self.ids = np.array([b.id for b in truth], dtype=np.int64)
        k = max((len(b.marker_ids) for b in truth), default=0)
        self.marker_ids = np.full((nb, k), -1, dtype=np.int64)
        for i, b in enumerate(truth):
            self.marker_ids[i, :len(b.marker_ids)] = b.marker_ids
        self.poses = np.stack([b.poses for b in truth]) if nb else np.zeros((0, 1, 4, 4))
        self._quats = None  # (bodies, frames, 4) x y z w, made when first needed
        self.valid = np.zeros(nb, dtype=np.int64)
        self.gross = np.zeros(nb, dtype=np.int64)
        self.scored = np.zeros(nb, dtype=np.int64)  # valid frames within the gross limits
        self.pos_sq = np.zeros(nb)  # sums over scored frames, m^2 and deg^2
        self.ang_sq = np.zeros(nb)
        self.ang_max = np.zeros(nb)
        self.swapped = np.zeros(nb, dtype=bool)
        self.frames = 0
        self.last_label = np.full(1024, -1, dtype=np.int64)  # by track id; -1 never labelled
        self.track_swaps = 0
        self.body_swaps = 0

    def __call__(self, result) -> None:
        if result.scene_frame < 0:
            return
        self.frames += 1
        if self.frames <= self.skip:
            return
        labelled = self._tracks(result)
        p = result.poses
        if not len(self.ids) or not len(p.ids):
            return
        same = self.ids[:, None] == p.ids[None, :]  # (truth bodies, posed bodies)
        row = np.argmax(same, axis=1)
        ok = same.any(axis=1) & p.valid[row]
        if not ok.any():
            return
        if self.slots and labelled is not None:
            ids, labels = labelled
            k = min(p.tracks.shape[1], self.marker_ids.shape[1])
            tids = p.tracks[row, :k]
            if len(ids):
                at = np.minimum(np.searchsorted(ids, tids), len(ids) - 1)
                got = np.where((tids >= 0) & (ids[at] == tids), labels[at], -1)
            else:
                got = np.full(tids.shape, -1)
            want = self.marker_ids[:, :k]
            wrong = np.any((got >= 0) & (want >= 0) & (got != want), axis=1)
            self.body_swaps += int(np.sum(ok & wrong & ~self.swapped))
            self.swapped[ok] = wrong[ok]
        R_true, t_true = self._truth_at(result)
        e = np.linalg.norm(p.position[row] - t_true, axis=1)
        cos = (np.einsum("bij,bij->b", p.rotation[row], R_true) - 1) / 2
        a = np.degrees(np.arccos(np.clip(cos, -1, 1)))
        self.valid += ok
        gross = ok & ((e > 0.02) | (a > 5.0))
        self.gross += gross
        good = ok & ~gross
        self.scored += good
        self.pos_sq[good] += e[good] ** 2
        self.ang_sq[good] += a[good] ** 2
        self.ang_max[good] = np.maximum(self.ang_max[good], a[good])

    def _truth_at(self, result):
        """The bodies' true (R, t) when the frame set was taken. Live, a set's time may lie
        between two scene frames: unsynchronised cameras (the set's median capture time), or
        the greedy multiplexer (the newest camera's time, the others moved to it); the truth
        is then interpolated (positions linearly, orientations by normalised quaternions),
        as the simulator rendered each camera's view."""
        f = result.scene_frame
        T = self.poses[:, f]
        t0 = getattr(self.scene, "t0_ns", None)
        if t0 is None:  # not a live run: sets are taken at their frame's time
            return T[:, :3, :3], T[:, :3, 3]
        period = 1e9 / self.scene.fps
        at = f + (result.t_ns - t0 - result.frame * period) / period
        last = self.poses.shape[1] - 1
        if abs(at - f) < 1e-6 or last < 1:
            return T[:, :3, :3], T[:, :3, 3]
        base = int(min(max(np.floor(at), 0), last - 1))
        w = at - base
        if self._quats is None:
            from scipy.spatial.transform import Rotation

            R = self.poses[:, :, :3, :3]
            self._quats = Rotation.from_matrix(R.reshape(-1, 3, 3)).as_quat().reshape(
                R.shape[:2] + (4,))
        qa, qb = self._quats[:, base], self._quats[:, base + 1]
        qb = qb * np.sign(np.sum(qa * qb, axis=1, keepdims=True) + 1e-12)
        q = (1 - w) * qa + w * qb
        q /= np.linalg.norm(q, axis=1, keepdims=True)
        pos = (1 - w) * self.poses[:, base, :3, 3] + w * self.poses[:, base + 1, :3, 3]
        return matrix_from_quaternion(q), pos

    def _tracks(self, result):
        """This frame's track identities (track ids sorted, true markers); counts track
        swaps. None without the simulator's blob labels."""
        marker = result.blob_marker
        if marker is None:
            return None
        tb = result.tracks.blobs
        lab = np.where(tb >= 0, marker[np.maximum(tb, 0)], -1)  # (T, C)
        # the most frequent label of each row, vectorised: count equal entries per cell
        same = (lab[:, :, None] == lab[:, None, :]) & (lab[:, None, :] >= 0)
        votes = np.where(lab >= 0, same.sum(axis=2), 0)
        best = lab[np.arange(len(lab)), np.argmax(votes, axis=1)] if len(lab) else lab[:, 0]
        has = best >= 0
        ids, best = result.tracks.ids[has], best[has]
        if len(ids) and ids[-1] >= len(self.last_label):  # track ids only grow
            grown = np.full(max(2 * len(self.last_label), int(ids[-1]) + 1), -1, np.int64)
            grown[:len(self.last_label)] = self.last_label
            self.last_label = grown
        before = self.last_label[ids]
        self.track_swaps += int(np.sum((before >= 0) & (before != best)))
        self.last_label[ids] = best  # the latest label of every track ever labelled
        return ids, best

    def figures(self) -> dict:
        n = max(self.frames - self.skip, 1)
        bodies = {}
        for i, b in enumerate(self.scene.bodies_truth):
            m = self.scored[i]
            bodies[b.name] = {
                "id": b.id,
                "valid_fraction": int(self.valid[i]) / n,
                "gross_error_frames": int(self.gross[i]),
                "position_error_mm_rms": float(np.sqrt(self.pos_sq[i] / m) * 1000) if m
                else None,
                "orientation_error_deg_rms": float(np.sqrt(self.ang_sq[i] / m)) if m else None,
                "orientation_error_deg_max": float(self.ang_max[i]) if m else None,
            }
        m = int(self.scored.sum())
        return {
            "frames_scored": n,
            "bodies": bodies,
            "position_error_mm_rms": float(np.sqrt(self.pos_sq.sum() / m) * 1000) if m
            else None,
            "orientation_error_deg_rms": float(np.sqrt(self.ang_sq.sum() / m)) if m else None,
            "track_swaps": self.track_swaps,
            "body_swaps": self.body_swaps,
            "gross_error_frames": int(self.gross.sum()),
        }
