"""The live pipeline: capture threads -> multiplexer -> tracker -> rigid bodies -> publishers.

One capture thread per camera reads its blob source (daemon.capture.sources) and pushes samples to
the multiplexer; a camera that fails is logged, closed and reopened while the others go on.
The multiplexer (daemon.capture.multiplexer) pairs samples into frame sets by capture time, never
by frame counter. The frame loop, on the caller's thread, tracks, poses, runs the
per-frame hooks and hands each result to every publisher's queue. Nothing here sees the
simulator's truth: scorers find it from the samples (daemon.synthetic).

The per-frame hook (`Pipeline.hooks`, callables taking a FrameResult) is where later
stages plug in (marker-set labelling, recorders, evaluation); hooks run on the frame loop
and must be quick, or hand work to a thread of their own as publishers do. Work that only
reads the results and need not keep up frame by frame (the simulator's scorers) goes in
`idle_hooks`: the results wait in a queue and the frame loop runs them while no frame
set is waiting (`run_idle`), so they never stand between a set's arrival and its poses
(nor hold the interpreter's lock against it, as a thread of their own would).
"""

from __future__ import annotations

import logging
import random
import threading
import time
from collections import deque
from dataclasses import dataclass

import numpy as np

from daemon.capture.multiplexer import FrameSet, Multiplexer, blob_velocity
from daemon.process.worker import Worker
from daemon.tracking.rigid import BodyPoses, RigidTracker
from daemon.tracking.tracker import Tracker, TrackFrame

__all__ = ["CaptureThread", "FrameResult", "FrameSet", "Multiplexer", "Pipeline", "Stats",
           "blob_velocity", "latency_figures"]

log = logging.getLogger("mocapd.pipeline")
IDLE_BACKLOG = 2400  # results waiting for the idle hooks; past this they run at once
SAMPLE_FRAMES = 65536  # frames the run's latency figures are kept for (Stats)


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
    samples: list | None = None
    labelled: object | None = None  # what the labelling stage made of the tracks, if any
    pickup_ns: int = 0  # when the frame loop started on the set
    published_ns: int = 0  # when every output had been handed the result

    def held_by_bodies(self) -> np.ndarray:
        """(T,) whether a rigid body holds each track this frame."""
        taken = self.poses.tracks
        return np.isin(self.tracks.ids, taken[taken >= 0])


# ---- capture ---------------------------------------------------------------------------------

class CaptureThread(Worker):
    """Reads one camera's blob source; on failure logs, waits and reopens."""

    def __init__(self, source, push, retry_s: float = 0.2, on_open=None) -> None:
        self.source, self.push, self.retry_s = source, push, retry_s
        # called with the camera before the first sample of every open: a reopened camera
        # counts frames from 0 again, maybe on a new clock epoch
        self.on_open = on_open
        self.name = source.name
        self.connected = False
        self.frames = 0
        self.failures = 0
        self.last_error = ""
        self.times: deque = deque(maxlen=256)
        super().__init__(f"cam-{self.name}")

    def rate_hz(self) -> float:
        t = list(self.times)
        if len(t) < 2 or time.monotonic_ns() - t[-1] > 1e9:
            return 0.0
        return (len(t) - 1) / max((t[-1] - t[0]) * 1e-9, 1e-9)

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                first = True
                for sample in self.source.open():
                    if first:
                        first = False
                        if self.on_open is not None:
                            self.on_open(sample.camera)
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


# ---- the frame loop ----------------------------------------------------------------------------

class Stats:
    """Rate and latency figures over the recent frames, and a bounded sample of the whole run.

    Why bounded: the daemon runs for days; per-frame lists for the whole run grew by about
    5 MB a minute at 240 fps (issue 30). The run's latency, markers and stage times are kept
    exactly for the first `sample_size` (SAMPLE_FRAMES) frames, then as a uniform reservoir
    sample of every frame since the start (Vitter's algorithm R: frame n replaces a random
    slot with probability size/n), so the median and p99 of `mocapd start --json` stay
    those of the whole run within sampling error (p99 from 65536 samples: within about
    0.04 percentile points). Slot i holds frame i or a later one, so `stage_ns[skip:]`
    never holds the first `skip` frames (tracks being found). Counts (frames, per-body valid
    frames)
    are running sums, exact."""

    def __init__(self, window: int = 2048, sample_size: int | None = None,
                 seed: int = 0) -> None:
        self.frames = 0
        self.done: deque = deque(maxlen=window)  # done_ns
        self.latency: deque = deque(maxlen=window)  # arrival -> poses, ns
        self.valid_bodies = 0
        self.body_valid: dict[int, int] = {}  # body id -> frames it was valid
        self.body_frames: dict[int, int] = {}
        # per sampled frame: latency, markers seen, then ns of capture, the set complete,
        # the frame loop picks it up, poses, outputs handed over (the stage figures)
        self.sample_size = SAMPLE_FRAMES if sample_size is None else sample_size
        self._sample = np.zeros((self.sample_size, 7), dtype=np.int64)  # pages touched when used
        self._kept = 0
        self._rng = random.Random(seed)

    @property
    def all_latency(self) -> np.ndarray:
        """Arrival -> poses of the sampled frames, ns (the whole run's, for --json)."""
        return self._sample[:self._kept, 0]

    @property
    def markers_seen(self) -> np.ndarray:
        return self._sample[:self._kept, 1]

    @property
    def stage_ns(self) -> np.ndarray:
        """(n, 5): capture, set complete, pickup, poses, outputs, ns, of the sampled frames."""
        return self._sample[:self._kept, 2:]

    def add(self, result: FrameResult) -> None:
        self.frames += 1
        self.done.append(result.done_ns)
        lat = result.done_ns - result.arrival_ns
        self.latency.append(lat)
        self.valid_bodies = int(np.sum(result.poses.valid))
        for i, v in zip(result.poses.ids.tolist(), result.poses.valid.tolist(), strict=True):
            self.body_valid[i] = self.body_valid.get(i, 0) + v
            self.body_frames[i] = self.body_frames.get(i, 0) + 1
        if self._kept < self.sample_size:
            slot = self._kept
            self._kept += 1
        else:
            slot = self._rng.randrange(self.frames)
            if slot >= self.sample_size:
                return
        self._sample[slot] = (lat, int(np.sum(result.tracks.seen)), result.t_ns,
                              result.arrival_ns, result.pickup_ns, result.done_ns,
                              result.published_ns)

    def rate_hz(self) -> float:
        d = list(self.done)
        if len(d) < 2:
            return 0.0
        return (len(d) - 1) / max((d[-1] - d[0]) * 1e-9, 1e-9)


STAGES = ("delivery", "pickup", "compute", "outputs")


def latency_stage_figures(stage_ns, skip: int = 0) -> dict:
    """Where a frame's latency goes, in ms: delivery (capture to the set's last sample
    arriving: the camera's transfer and its capture thread), pickup (the set complete to the
    frame loop starting on it), compute (tracking, bodies, labelling), outputs (handing the
    result over, inline sends included). Median and p99 of each, and the mean of each over
    the slowest 1 % of frames (capture to outputs), which says what the tail waits for.
    `skip` leaves out the first frames (tracks being found)."""
    a = np.asarray(stage_ns[skip:], dtype=np.float64).reshape(-1, 5)
    if not len(a):
        return {}
    parts = np.diff(a, axis=1) * 1e-6
    total = (a[:, 4] - a[:, 0]) * 1e-6
    tail = total >= np.percentile(total, 99)
    out = {"total": {"median_ms": float(np.median(total)),
                     "p99_ms": float(np.percentile(total, 99))}}
    for k, name in enumerate(STAGES):
        out[name] = {"median_ms": float(np.median(parts[:, k])),
                     "p99_ms": float(np.percentile(parts[:, k], 99)),
                     "slowest_1pct_mean_ms": float(parts[tail, k].mean())}
    return out


def latency_figures(latency_ns) -> dict:
    a = np.asarray(latency_ns if isinstance(latency_ns, np.ndarray) else list(latency_ns),
                   dtype=np.float64) * 1e-6
    if not len(a):
        return {"median_ms": None, "p99_ms": None, "max_ms": None, "count": 0}
    return {"median_ms": float(np.median(a)), "p99_ms": float(np.percentile(a, 99)),
            "max_ms": float(a.max()), "count": int(len(a))}


class _IdleCall:
    """A call queued among the idle path's results (Pipeline.replace's idle_call)."""

    def __init__(self, call) -> None:
        self.call = call


def retire(parts: list) -> None:
    """Stop what a reload replaced (outputs flush and close; a labelling stage closes)."""
    for part in parts:
        try:
            part.stop() if hasattr(part, "stop") else part.close()
        except Exception:  # noqa: BLE001 - one output failing to stop must not keep the rest
            log.exception("stopping a replaced output")


class Pipeline:
    """The tracker and rigid bodies over frame sets; results to hooks and publishers."""

    def __init__(self, rig, tracker_config, rigid_config, bodies, publishers=(),
                 hooks=(), labeller=None, idle_hooks=()) -> None:
        self.rig = rig
        self.tracker = Tracker(rig, tracker_config)
        self.rigid = RigidTracker(list(bodies), rigid_config)
        self.publishers = list(publishers)
        self.hooks = list(hooks)
        self.idle_hooks = list(idle_hooks)  # run from run_idle, off the latency path
        self._idle: deque = deque()  # results the idle hooks have not seen yet
        # CPU time the idle hooks took (the simulator's scorers: a real rig has none), so the
        # benchmarks can state the daemon's own cost per frame apart from the scoring's
        self.idle_cpu_ns = 0
        # optional stage between the rigid bodies and the outputs: labeller(result) returns
        # what is stored in result.labelled (named markers when a marker set is configured)
        self.labeller = labeller
        self.stats = Stats()
        self._lock = threading.Lock()
        self._pending_bodies = None
        self._pending_publishers = None
        self._pending_labeller = None
        self._pending_tracker = None
        self._pending_idle_call = None
        self._retired: list = []  # outputs and labelling stages a swap replaced, to stop
        self.swapped = threading.Event()  # set once the frame loop has applied a replace()
        self._published = threading.Event()  # set as each frame is done (outputs and all)
        self._period_anchor: tuple[int, int] | None = None  # (index, t_ns) of a set
        self.last_result: FrameResult | None = None

    def replace(self, bodies=None, publishers=None, labeller=..., tracker=None,
                idle_call=None, seeds=None) -> None:
        """New rigid bodies, publishers, labelling stage (None: labelling off) and/or tracker
        (a new rig or gates) from a reload; applied between two frames by the frame loop, so
        the stream never stops. `idle_call()` runs on the idle path once every result
        tracked before the swap has been there (a scorer switching to the new bodies);
        `seeds` are where new bodies were found among the tracks (RigidTracker.seed)."""
        with self._lock:
            if tracker is not None:
                self._pending_tracker = tracker
            if labeller is not ...:
                self._supersede(self._pending_labeller, [labeller])
                self._pending_labeller = (labeller,)
            if bodies is not None:
                self._pending_bodies = (list(bodies), seeds)
            if publishers is not None:
                self._supersede(self._pending_publishers, publishers)
                self._pending_publishers = list(publishers)
            if idle_call is not None:
                self._pending_idle_call = idle_call
            self.swapped.clear()

    def _supersede(self, pending, now) -> None:
        """A replace() not swapped in yet, replaced by another: what it built and the new
        one does not keep is stopped too."""
        if pending is not None:
            keep = {id(x) for x in (*now, *self.publishers, self.labeller)}
            self._retired += [x for x in pending if x is not None and id(x) not in keep]

    @property
    def swap_pending(self) -> bool:
        return (self._pending_bodies is not None or self._pending_publishers is not None
                or self._pending_labeller is not None or self._pending_tracker is not None)

    def _apply_pending(self) -> None:
        """The swap, on the frame loop's thread. Only what is quick happens here: a new
        server that takes over its predecessor's sockets starts (every other new output was
        started beside the stream), and what was replaced is left for the reload's thread to
        stop (`take_retired`): an output's stop waits for its worker to flush."""
        with self._lock:
            bodies, pubs = self._pending_bodies, self._pending_publishers
            labeller, tracker = self._pending_labeller, self._pending_tracker
            idle_call = self._pending_idle_call
            self._pending_bodies = self._pending_publishers = self._pending_labeller = None
            self._pending_tracker = self._pending_idle_call = None
        retired: list = []
        if tracker is not None:
            if getattr(tracker, "carry", False):  # same rig, new gates: the tracks go on
                tracker.carry_tracks(self.tracker)
            tracker.period_s = self.tracker.period_s
            self.tracker, self.rig = tracker, tracker.rig
        if labeller is not None:
            if labeller[0] is not self.labeller and hasattr(self.labeller, "close"):
                retired.append(self.labeller)  # a start still searching on its thread stops
            self.labeller = labeller[0]
        if bodies is not None:
            self.rigid.set_bodies(*bodies)
        if pubs is not None:
            for p in pubs:
                if not p.started:  # a server taking over its predecessor's sockets
                    p.start()
            now = {id(p) for p in pubs}
            retired += [p for p in self.publishers if id(p) not in now]
            self.publishers = pubs
        if idle_call is not None:
            if self.idle_hooks:
                self._idle.append(_IdleCall(idle_call))
            else:
                idle_call()
        with self._lock:
            self._retired += retired
        self.swapped.set()

    def after_frame(self, timeout_s: float) -> None:
        """Return just after the frame loop is done with the next frame, its outputs sent
        (or after `timeout_s` with no frame): work beside the stream done then (a reload's
        steps) has the gap until the next frame to itself instead of slowing the frame
        loop and the cameras' threads, which share the interpreter with it."""
        self._published.clear()
        self._published.wait(timeout_s)

    def take_retired(self) -> list:
        """What swaps replaced and nobody has stopped yet (the reload that asked stops it)."""
        with self._lock:
            parts, self._retired = self._retired, []
        return parts

    def apply_pending(self) -> None:
        """A waiting swap applied now: the frame loop calls it while no frames come (every
        camera gone), so a reload still takes effect; only from the frame loop's thread."""
        if self.swap_pending:
            self._apply_pending()

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
        pickup_ns = time.monotonic_ns()
        if self.swap_pending:
            self._apply_pending()
        samples = fs.samples
        if samples:
            # one repeat, not an array per camera: at 32 cameras that was most of this
            # method's own time (issue 33)
            camera = np.repeat(np.fromiter((s.camera for s in samples), np.int64, len(samples)),
                               [len(s.uv) for s in samples])
            uv = np.concatenate([s.uv for s in samples])
            area = np.concatenate([s.area for s in samples])  # merged blobs show by their size
        else:
            camera, uv, area = np.zeros(0, np.int64), np.zeros((0, 2)), np.zeros(0)
        self._learn_period(fs)
        tracks = self.tracker.update(camera, uv, fs.t_ns, area)
        poses = self.rigid.update(tracks, uv, self.tracker.cams)
        result = FrameResult(fs.index, fs.t_ns, fs.arrival_ns, time.monotonic_ns(), camera, uv,
                             tracks, poses, samples, pickup_ns=pickup_ns)
        if self.labeller is not None:
            result.labelled = self.labeller(result)
            result.done_ns = time.monotonic_ns()
        for p in self.publishers:
            p.submit(result)
        result.published_ns = time.monotonic_ns()
        # for the next frame only (the result holds copies): after the outputs, off the
        # latency path
        self.tracker.place(*self.rigid.hidden_markers(tracks))
        for hook in self.hooks:
            hook(result)
        if self.idle_hooks:
            self._idle.append(result)
            if len(self._idle) > IDLE_BACKLOG:  # never idle: keep the queue bounded
                self.run_idle(len(self._idle) - IDLE_BACKLOG)
        self.stats.add(result)
        self.last_result = result
        self._published.set()  # the frame loop is done with it: a reload's step may go
        return result

    @property
    def idle_pending(self) -> int:
        """Results the idle hooks have still to see."""
        return len(self._idle)

    def run_idle(self, n: int | None = None) -> None:
        """Hand up to `n` waiting results (all when None) to the idle hooks, oldest first."""
        k = len(self._idle) if n is None else min(n, len(self._idle))
        for _ in range(k):
            result = self._idle.popleft()
            if isinstance(result, _IdleCall):
                result.call()
                continue
            t0 = time.thread_time_ns()
            for hook in self.idle_hooks:
                hook(result)
            self.idle_cpu_ns += time.thread_time_ns() - t0
