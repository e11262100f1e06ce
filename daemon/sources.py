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
from daemon.rigid import BodyDef

log = logging.getLogger("mocapd.sources")

PLUGINS = {"basler": "pypylon", "genicam": "harvesters"}


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
        self.truth = truth
        obs = sim.observe(self.truth_rig, truth, noise_px=cfg.noise_px, dropout=cfg.dropout,
                          ghosts_per_camera=cfg.ghosts, fps=cfg.fps, seed=cfg.seed + 3)
        self.obs = obs.sorted()
        key = self.obs.frame * len(rig) + self.obs.camera
        self.starts = np.searchsorted(key, np.arange(n * len(rig) + 1))

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


class SimCamera:
    """One simulated (or replayed) camera as a capture thread reads it: paced at the
    scene's rate from a shared start time, so all cameras' frame i share one capture time
    (a triggered rig). A replay ends with its recording."""

    def __init__(self, scene: SimScene, camera: int, t0_ns: int) -> None:
        self.scene, self.camera, self.t0_ns = scene, camera, t0_ns
        self.name = scene.rig.names[camera]

    def open(self) -> Iterator[CameraSample]:
        period = 1e9 / self.scene.fps
        i = max(0, int(np.ceil((time.monotonic_ns() - self.t0_ns) / period)))
        end = getattr(self.scene, "frame_numbers", None)
        while end is None or i < len(end):
            due = self.t0_ns + round(i * period)
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
    """

    def __init__(self, scene: SimScene, skip_frames: int = 5, slots: bool = True) -> None:
        self.scene = scene
        self.skip = skip_frames
        self.slots = slots
        self.ids = [b.id for b in scene.bodies_truth]
        self.pos_sq = {i: [] for i in self.ids}
        self.ang = {i: [] for i in self.ids}
        self.valid = dict.fromkeys(self.ids, 0)
        self.gross = dict.fromkeys(self.ids, 0)
        self.frames = 0
        self.prev_ids = np.zeros(0, dtype=np.int64)  # tracks labelled so far, sorted
        self.prev_labels = np.zeros(0, dtype=np.int64)
        self.track_swaps = 0
        self.swapped = dict.fromkeys(self.ids, False)
        self.body_swaps = 0

    def __call__(self, result) -> None:
        if result.scene_frame < 0:
            return
        self.frames += 1
        if self.frames <= self.skip:
            return
        labels = self._tracks(result)
        p = result.poses
        f = result.scene_frame
        for b in self.scene.bodies_truth:
            hit = np.flatnonzero(p.ids == b.id)
            if not len(hit) or not p.valid[hit[0]]:
                continue
            i = hit[0]
            if self.slots and labels is not None:
                tids = p.tracks[i, :len(b.marker_ids)]
                got = np.array([labels.get(int(t), -1) for t in tids])
                wrong = bool(np.any((got >= 0) & (got != b.marker_ids)))
                self.body_swaps += wrong and not self.swapped[b.id]
                self.swapped[b.id] = wrong
            T = b.poses[f]
            e = float(np.linalg.norm(p.position[i] - T[:3, 3]))
            cos = (np.trace(p.rotation[i] @ T[:3, :3].T) - 1) / 2
            a = float(np.degrees(np.arccos(np.clip(cos, -1, 1))))
            self.valid[b.id] += 1
            if e > 0.02 or a > 5.0:
                self.gross[b.id] += 1
                continue
            self.pos_sq[b.id].append(e * e)
            self.ang[b.id].append(a)

    def _tracks(self, result) -> dict | None:
        """This frame's track identities {track id: true marker}; counts track swaps."""
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
        if len(self.prev_ids) and len(ids):
            pos = np.minimum(np.searchsorted(self.prev_ids, ids), len(self.prev_ids) - 1)
            known = self.prev_ids[pos] == ids
            self.track_swaps += int(np.sum(known & (self.prev_labels[pos] != best)))
        # remember the latest label of every track ever labelled
        keep = ~np.isin(self.prev_ids, ids)
        self.prev_ids = np.concatenate([self.prev_ids[keep], ids])
        self.prev_labels = np.concatenate([self.prev_labels[keep], best])
        order = np.argsort(self.prev_ids)
        self.prev_ids, self.prev_labels = self.prev_ids[order], self.prev_labels[order]
        return dict(zip(ids.tolist(), best.tolist(), strict=True))

    def figures(self) -> dict:
        n = max(self.frames - self.skip, 1)
        bodies = {}
        for b in self.scene.bodies_truth:
            pos = np.array(self.pos_sq[b.id])
            ang = np.array(self.ang[b.id])
            bodies[b.name] = {
                "id": b.id,
                "valid_fraction": self.valid[b.id] / n,
                "gross_error_frames": self.gross[b.id],
                "position_error_mm_rms": float(np.sqrt(pos.mean()) * 1000) if len(pos) else None,
                "orientation_error_deg_rms": float(np.sqrt(np.mean(ang**2))) if len(ang)
                else None,
                "orientation_error_deg_max": float(ang.max()) if len(ang) else None,
            }
        all_pos = np.concatenate([np.array(v) for v in self.pos_sq.values()] or [np.zeros(0)])
        all_ang = np.concatenate([np.array(v) for v in self.ang.values()] or [np.zeros(0)])
        return {
            "frames_scored": n,
            "bodies": bodies,
            "position_error_mm_rms": float(np.sqrt(all_pos.mean()) * 1000) if len(all_pos)
            else None,
            "orientation_error_deg_rms": float(np.sqrt(np.mean(all_ang**2))) if len(all_ang)
            else None,
            "track_swaps": self.track_swaps,
            "body_swaps": self.body_swaps,
            "gross_error_frames": sum(self.gross.values()),
        }
