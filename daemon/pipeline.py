"""The live pipeline: capture threads -> multiplexer -> tracker -> rigid bodies -> publishers.

One capture thread per camera reads its blob source (daemon.sources) and pushes samples to
the multiplexer; a camera that fails is logged, closed and reopened while the others go on.
The multiplexer makes frame sets: "triggered" waits for every connected camera's sample of
a frame (hardware-synchronised cameras), up to timeout_frames periods; "greedy" emits as
soon as any camera reports, with the other cameras' blobs extrapolated to that time from
their 2D motion (free-running cameras). The frame loop, on the caller's thread, tracks,
poses, runs the per-frame hooks and hands each result to every publisher's queue.

The per-frame hook (`Pipeline.hooks`, callables taking a FrameResult) is where later
stages plug in (marker-set labelling, recorders, evaluation); hooks run on the frame loop
and must be quick, or hand work to a thread of their own as publishers do.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from dataclasses import dataclass

import numpy as np

from daemon.rigid import BodyPoses, RigidTracker
from daemon.sources import CameraSample
from daemon.tracker import Tracker, TrackFrame

log = logging.getLogger("mocapd.pipeline")


@dataclass(eq=False)
class FrameSet:
    """Samples of one frame from the cameras that delivered them."""

    index: int
    t_ns: int
    arrival_ns: int  # when the set was complete (the last sample's arrival)
    samples: list[CameraSample]


@dataclass(eq=False)
class FrameResult:
    """What one frame produced: handed to hooks and publishers."""

    frame: int
    t_ns: int
    arrival_ns: int
    done_ns: int
    camera: np.ndarray  # (M,) blobs of the frame
    uv: np.ndarray
    tracks: TrackFrame
    poses: BodyPoses
    blob_marker: np.ndarray | None = None  # (M,) true markers (simulator)
    scene_frame: int = -1
    samples: list | None = None
    labelled: object | None = None  # what the labelling stage made of the tracks, if any


# ---- capture ---------------------------------------------------------------------------------

class CaptureThread:
    """Reads one camera's blob source; on failure logs, waits and reopens."""

    def __init__(self, source, push, retry_s: float = 0.2) -> None:
        self.source, self.push, self.retry_s = source, push, retry_s
        self.name = source.name
        self.connected = False
        self.frames = 0
        self.failures = 0
        self.last_error = ""
        self.times: deque = deque(maxlen=256)
        self._stop = threading.Event()
        self.thread = threading.Thread(target=self._run, name=f"cam-{self.name}", daemon=True)

    def start(self) -> None:
        self.thread.start()

    def stop(self) -> None:
        self._stop.set()

    def join(self, timeout: float = 1.0) -> None:
        self.thread.join(timeout)

    def rate_hz(self) -> float:
        t = list(self.times)
        if len(t) < 2 or time.monotonic_ns() - t[-1] > 1e9:
            return 0.0
        return (len(t) - 1) / max((t[-1] - t[0]) * 1e-9, 1e-9)

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                for sample in self.source.open():
                    if not self.connected:
                        self.connected = True
                        if self.failures:
                            log.warning("%s: reconnected", self.name)
                    self.frames += 1
                    self.times.append(sample.arrival_ns)
                    self.push(sample)
                    if self._stop.is_set():
                        break
                else:
                    log.warning("%s: source ended", self.name)
                    self.connected = False
                    return
            except Exception as exc:  # noqa: BLE001 - any camera failure: log, reopen
                self.failures += 1
                if self.connected or str(exc) != self.last_error:
                    log.warning("%s: %s; reopening", self.name, exc)
                self.last_error = str(exc)
                self.connected = False
                self._stop.wait(self.retry_s)


# ---- multiplexer -----------------------------------------------------------------------------

GREEDY_MATCH_PX = 20.0  # farthest a blob moves between two samples of its camera


def _match(a: np.ndarray, b: np.ndarray, gate_px: float) -> np.ndarray:
    """For each blob of `a`, its nearest blob in `b` within the gate, or -1. (Requiring
    mutual and unambiguous matches was tried: the blobs it left without a velocity, used
    where they were seen, gave more swaps than the odd wrong match.)"""
    j = np.full(len(a), -1, dtype=np.int64)
    if not len(a) or not len(b):
        return j
    d2 = np.sum((a[:, None, :] - b[None, :, :]) ** 2, axis=2)
    near = np.argmin(d2, axis=1)
    ok = d2[np.arange(len(a)), near] < gate_px * gate_px
    j[ok] = near[ok]
    return j


def blob_velocity(hist: list) -> np.ndarray:
    """Pixels per ns of each blob of the newest sample in `hist` (a camera's last 2-3
    samples): from its match in the previous sample, averaged with the previous step's
    when that blob was matched there too (half the noise of a two-sample difference);
    zero for a blob with no match (it is used where it was seen)."""
    cur, prev = hist[-1], hist[-2]
    vel = np.zeros_like(cur.uv)
    if cur.t_ns <= prev.t_ns:
        return vel
    j = _match(cur.uv, prev.uv, GREEDY_MATCH_PX)
    has = j >= 0
    vel[has] = (cur.uv[has] - prev.uv[j[has]]) / (cur.t_ns - prev.t_ns)
    if len(hist) >= 3 and hist[-3].t_ns < prev.t_ns and np.any(has):
        old = hist[-3]
        k = _match(prev.uv, old.uv, GREEDY_MATCH_PX)
        both = np.flatnonzero(has)
        both = both[k[j[both]] >= 0]
        if len(both):
            step = (prev.uv[j[both]] - old.uv[k[j[both]]]) / (prev.t_ns - old.t_ns)
            vel[both] = 0.5 * (vel[both] + step)
    return vel


class Multiplexer:
    """Frame sets from camera samples, `triggered` or `greedy` (see the module docstring)."""

    def __init__(self, n_cameras: int, mode: str = "triggered", fps: float = 240.0,
                 timeout_frames: float = 1.5, connected=None) -> None:
        self.n = n_cameras
        self.mode = mode
        self.timeout_ns = int(timeout_frames * 1e9 / fps)
        self.connected = connected or (lambda: np.ones(n_cameras, dtype=bool))
        self.cond = threading.Condition()
        self.pending: dict[int, dict[int, CameraSample]] = {}
        self.first_arrival: dict[int, int] = {}
        self.need: dict[int, list[int]] = {}  # per pending frame: the cameras it waits for
        self.ready: deque = deque(maxlen=64)
        self.last_emitted = -1
        self.incomplete = 0  # sets emitted on timeout, missing a camera
        self.late = 0  # samples that came after their frame was emitted
        self.overflow = 0
        self.skipped = 0  # sets dropped by the frame loop to stay live (it fell behind)
        self.max_backlog = 2
        self.missing = np.zeros(n_cameras, dtype=np.int64)  # per camera: frames missed
        self.latest: list[list[CameraSample]] = [[] for _ in range(n_cameras)]

    def push(self, sample: CameraSample) -> None:
        with self.cond:
            if self.mode == "greedy":
                hist = self.latest[sample.camera]
                hist.append(sample)
                del hist[:-3]
                self._put(self._greedy_set(sample))
                return
            if sample.index <= self.last_emitted:
                self.late += 1
                return
            group = self.pending.get(sample.index)
            if group is None:
                # which cameras this frame waits for: asked once per frame, not per sample
                # (eight threads push in turn; every microsecond here is latency)
                group = self.pending[sample.index] = {}
                self.first_arrival[sample.index] = sample.arrival_ns
                self.need[sample.index] = np.flatnonzero(self.connected()).tolist()
            group[sample.camera] = sample
            if len(group) == self.n or all(c in group for c in self.need[sample.index]):
                self._emit(sample.index)

    def _put(self, fs: FrameSet) -> None:
        if len(self.ready) == self.ready.maxlen:
            self.overflow += 1
        self.ready.append(fs)
        self.cond.notify()

    def _emit(self, index: int) -> None:
        # anything older than this frame will never complete now
        for old in [i for i in self.pending if i < index]:
            self._emit_group(old)
        self._emit_group(index)

    def _emit_group(self, index: int) -> None:
        group = self.pending.pop(index)
        self.first_arrival.pop(index, None)
        self.need.pop(index, None)
        if index <= self.last_emitted:
            return
        self.last_emitted = index
        samples = [group[c] for c in sorted(group)]
        if len(samples) < self.n:
            self.incomplete += 1
            got = np.zeros(self.n, dtype=bool)
            got[list(group)] = True
            self.missing[~got] += 1
        ts = sorted(s.t_ns for s in samples)
        t = (ts[(len(ts) - 1) // 2] + ts[len(ts) // 2]) // 2  # the median capture time
        self._put(FrameSet(index, t, max(s.arrival_ns for s in samples), samples))

    def _expire(self, now_ns: int) -> None:
        for index in sorted(self.pending):
            if now_ns - self.first_arrival[index] >= self.timeout_ns:
                self._emit(index)

    def _greedy_set(self, newest: CameraSample) -> FrameSet:
        """Every camera's latest blobs, moved to the newest sample's time along their 2D
        velocity (see blob_velocity)."""
        t = newest.t_ns
        out = []
        for hist in self.latest:
            if not hist:
                continue
            cur = hist[-1]
            if cur is newest or len(hist) < 2 or cur.t_ns == t or not len(cur.uv):
                out.append(cur)
                continue
            vel = blob_velocity(hist)
            uv = cur.uv + vel * (t - cur.t_ns)
            out.append(CameraSample(cur.camera, newest.index, t, cur.arrival_ns, uv, cur.area,
                                    cur.peak, cur.marker, newest.scene_frame))
        return FrameSet(newest.index, t, newest.arrival_ns, out)

    def next(self, timeout_s: float = 0.2) -> FrameSet | None:
        """The next frame set, or None after timeout_s with nothing to give."""
        deadline = time.monotonic_ns() + int(timeout_s * 1e9)
        with self.cond:
            while True:
                if self.ready:
                    while len(self.ready) > self.max_backlog:
                        self.ready.popleft()
                        self.skipped += 1
                    return self.ready.popleft()
                now = time.monotonic_ns()
                if self.pending:
                    self._expire(now)
                    if self.ready:
                        continue
                if now >= deadline:
                    return None
                wait = deadline - now
                if self.first_arrival:
                    wait = min(wait, min(self.first_arrival.values()) + self.timeout_ns - now)
                self.cond.wait(max(wait, 0) * 1e-9 + 1e-5)


# ---- the frame loop ----------------------------------------------------------------------------

class Stats:
    """Rate and latency figures over the recent frames."""

    def __init__(self, window: int = 2048) -> None:
        self.frames = 0
        self.done: deque = deque(maxlen=window)  # done_ns
        self.latency: deque = deque(maxlen=window)  # arrival -> poses, ns
        self.all_latency: list[int] = []  # whole run, for the --json figures
        self.valid_bodies = 0
        self.body_valid: dict[int, int] = {}  # body id -> frames it was valid
        self.body_frames: dict[int, int] = {}
        self.markers_seen: list[int] = []

    def add(self, result: FrameResult) -> None:
        self.frames += 1
        self.done.append(result.done_ns)
        lat = result.done_ns - result.arrival_ns
        self.latency.append(lat)
        if len(self.all_latency) < 10_000_000:
            self.all_latency.append(lat)
        self.valid_bodies = int(np.sum(result.poses.valid))
        for i, v in zip(result.poses.ids.tolist(), result.poses.valid.tolist(), strict=True):
            self.body_valid[i] = self.body_valid.get(i, 0) + v
            self.body_frames[i] = self.body_frames.get(i, 0) + 1
        if len(self.markers_seen) < 10_000_000:
            self.markers_seen.append(int(np.sum(result.tracks.seen)))

    def rate_hz(self) -> float:
        d = list(self.done)
        if len(d) < 2:
            return 0.0
        return (len(d) - 1) / max((d[-1] - d[0]) * 1e-9, 1e-9)


def latency_figures(latency_ns) -> dict:
    a = np.asarray(list(latency_ns), dtype=np.float64) * 1e-6
    if not len(a):
        return {"median_ms": None, "p99_ms": None, "max_ms": None, "count": 0}
    return {"median_ms": float(np.median(a)), "p99_ms": float(np.percentile(a, 99)),
            "max_ms": float(a.max()), "count": int(len(a))}


class Pipeline:
    """The tracker and rigid bodies over frame sets; results to hooks and publishers."""

    def __init__(self, rig, tracker_config, rigid_config, bodies, publishers=(),
                 hooks=(), labeller=None) -> None:
        self.rig = rig
        self.tracker = Tracker(rig, tracker_config)
        self.rigid = RigidTracker(list(bodies), rigid_config)
        self.publishers = list(publishers)
        self.hooks = list(hooks)
        # optional stage between the rigid bodies and the outputs: labeller(result) returns
        # what is stored in result.labelled (named markers when a marker set is configured)
        self.labeller = labeller
        self.stats = Stats()
        self._lock = threading.Lock()
        self._pending_bodies = None
        self._pending_publishers = None
        self._pending_labeller = None
        self._period_anchor: tuple[int, int] | None = None  # (index, t_ns) of a set
        self.last_result: FrameResult | None = None

    def replace(self, bodies=None, publishers=None, labeller=...) -> None:
        """New rigid bodies, publishers and/or labelling stage (None: labelling off) from a
        reload; applied between two frames by the frame loop, so the stream never stops."""
        with self._lock:
            if labeller is not ...:
                self._pending_labeller = (labeller,)
            if bodies is not None:
                self._pending_bodies = list(bodies)
            if publishers is not None:
                self._pending_publishers = list(publishers)

    def _apply_pending(self) -> None:
        with self._lock:
            bodies, pubs = self._pending_bodies, self._pending_publishers
            labeller = self._pending_labeller
            self._pending_bodies = self._pending_publishers = self._pending_labeller = None
        if labeller is not None:
            self.labeller = labeller[0]
        if bodies is not None:
            self.rigid.set_bodies(bodies)
        if pubs is not None:
            old = self.publishers
            for p in pubs:
                p.start()
            self.publishers = pubs
            for p in old:
                p.stop()

    def _learn_period(self, fs: FrameSet) -> None:
        """The frame period from the sets' indices and times (what the tracker needs to
        weigh updates less than a frame apart): time over frames since an anchor set."""
        anchor = self._period_anchor
        if anchor is None or fs.index <= anchor[0] or fs.t_ns <= anchor[1]:
            self._period_anchor = (fs.index, fs.t_ns)
            return
        frames = fs.index - anchor[0]
        if frames >= 4:
            self.tracker.period_s = (fs.t_ns - anchor[1]) / frames * 1e-9
        if frames >= 4096:  # follow a drifting clock
            self._period_anchor = (fs.index, fs.t_ns)

    def process(self, fs: FrameSet) -> FrameResult:
        if (self._pending_bodies is not None or self._pending_publishers is not None
                or self._pending_labeller is not None):
            self._apply_pending()
        samples = fs.samples
        if samples:
            camera = np.concatenate([np.full(len(s.uv), s.camera, dtype=np.int64)
                                     for s in samples])
            uv = np.concatenate([s.uv for s in samples])
            marker = (np.concatenate([s.marker for s in samples])
                      if all(s.marker is not None for s in samples) else None)
        else:
            camera, uv, marker = np.zeros(0, np.int64), np.zeros((0, 2)), None
        self._learn_period(fs)
        tracks = self.tracker.update(camera, uv, fs.t_ns)
        poses = self.rigid.update(tracks, uv, self.tracker.cams)
        scene_frame = samples[0].scene_frame if samples else -1
        result = FrameResult(fs.index, fs.t_ns, fs.arrival_ns, time.monotonic_ns(), camera, uv,
                             tracks, poses, marker, scene_frame, samples)
        if self.labeller is not None:
            result.labelled = self.labeller(result)
            result.done_ns = time.monotonic_ns()
        for p in self.publishers:
            p.submit(result)
        # for the next frame only (the result holds copies): after the outputs, off the
        # latency path
        self.tracker.place(*self.rigid.hidden_markers(tracks))
        for hook in self.hooks:
            hook(result)
        self.stats.add(result)
        self.last_result = result
        return result
