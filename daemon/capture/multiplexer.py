"""The multiplexer: camera samples paired into frame sets by capture time.

Cameras open at different moments and count frames from their own start (and from 0 again
when they reopen), and those that stamp frames do so on clocks of their own; so a frame
counter says nothing about which frames of two cameras were taken together. Samples are
paired by capture time instead: each camera's timestamp or frame id is mapped to the
daemon's clock by an offset and drift learned online (daemon.capture.clocks), the source's own
time stands in for cameras that give neither, and a set gathers the samples within a
fraction of a frame period of each other. "triggered" waits for every connected camera's
sample of an instant (hardware-synchronised cameras), up to timeout_frames periods;
"greedy" emits as soon as any camera reports, with the other cameras' blobs extrapolated
to that time from their 2D motion (free-running cameras).
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from dataclasses import dataclass

import numpy as np

from daemon.capture.clocks import CameraClock
from daemon.capture.sources import CameraSample


@dataclass(eq=False)
class FrameSet:
    """Samples of one instant from the cameras that delivered them."""

    index: int  # the daemon's frame number: frame periods since it started
    t_ns: int  # the median of the samples' capture times (daemon clock)
    arrival_ns: int  # when the set was complete (the last sample's arrival)
    samples: list[CameraSample]


# ---- multiplexer -----------------------------------------------------------------------------

GREEDY_MATCH_PX = 20.0  # farthest a blob moves between two samples of its camera
DEADLINE_MAX_FRAMES = 4.0  # the longest a set waits for a camera, whatever the waits seen
DEADLINE_MARGIN_NS = 500_000  # added to the p99 of the waits complete sets took
DEADLINE_EVERY = 240  # complete sets between two refits of the deadline
BEHIND_SAY_S = 10.0  # the frame loop falling behind is logged at most this often
BEHIND_SHOWN_S = 5.0  # and shown in the status this long after its last skip
log = logging.getLogger("mocapd.multiplexer")


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


@dataclass(eq=False)
class _Group:
    """A frame set being gathered: samples of one instant, by camera."""

    t_ns: float  # the members' mean capture time
    total_ns: float
    samples: dict
    first_arrival: int
    waiting: set  # the cameras it still waits for (of those connected when it began)


class Multiplexer:
    """Frame sets from camera samples, `triggered` or `greedy` (see the module docstring).

    A sample's capture time comes from its camera's clock model (CameraClock) when the
    camera stamps its frames, else from the source. A triggered set gathers the samples
    within `tolerance_frames` periods of the members' mean time, one per camera; a sample
    older than the last set emitted (within that tolerance) is late and dropped."""

    def __init__(self, n_cameras: int, mode: str = "triggered", fps: float = 240.0,
                 timeout_frames: float = 1.5, connected=None,
                 tolerance_frames: float = 0.5, origin_ns: int | None = None) -> None:
        """`origin_ns`: when frame 0 was (the daemon's start); frame numbers count frame
        periods from it (from the first set if None)."""
        self.n = n_cameras
        self.origin_ns = origin_ns
        self.mode = mode
        self.period_ns = 1e9 / fps
        self.tol_ns = tolerance_frames * self.period_ns
        self.timeout_ns = int(timeout_frames * self.period_ns)
        # how long a set waits for its last camera: at least the configured timeout, more
        # when complete sets are seen to take longer (a node's batch behind a slow hop),
        # up to DEADLINE_MAX_FRAMES periods (see _fit_deadline)
        self.base_timeout_ns = self.timeout_ns
        self._waits: deque = deque(maxlen=2048)  # complete sets: first sample -> last, ns
        self.connected = connected or (lambda: np.ones(n_cameras, dtype=bool))
        self.cond = threading.Condition()
        self.clocks = [CameraClock(self.period_ns) for _ in range(n_cameras)]
        self.last_id = [-1] * n_cameras  # each camera's last device frame id
        self.frame_gaps = np.zeros(n_cameras, dtype=np.int64)  # frames its counter skipped
        self.pending: list[_Group] = []  # sets being gathered, oldest first
        self.ready: deque = deque(maxlen=64)
        self.last_t: float | None = None  # capture time of the newest set emitted
        self.last_index = -1
        self.incomplete = 0  # sets emitted on timeout, missing a camera
        self.late = 0  # samples that came after their instant's set was emitted
        self.settling = 0  # samples left out while their camera's clock settled
        self.overflow = 0
        self.skipped = 0  # sets dropped by the frame loop to stay live (it fell behind)
        self.max_backlog = 2
        self._made: deque = deque(maxlen=480)  # when the latest sets were made (ns)
        self._taken: deque = deque(maxlen=480)  # and when the frame loop took its latest
        self._skip_ns = 0  # the last skip
        self._said_ns = -(10**18)
        self._behind = ""
        self.missing = np.zeros(n_cameras, dtype=np.int64)  # per camera: sets without it
        self.latest: list[list[CameraSample]] = [[] for _ in range(n_cameras)]

    def reset_camera(self, camera: int) -> None:
        """The camera (re)opened: its counter starts again, its clock maybe on a new epoch."""
        with self.cond:
            self.clocks[camera].reset()
            self.last_id[camera] = -1
            self.latest[camera] = []

    def capture_ns(self, sample: CameraSample) -> int | None:
        """The sample's capture time on the daemon's clock: its device time (or frame id)
        through its camera's clock model, or the source's own estimate; None while the
        camera's clock has just (re)started and cannot be trusted yet."""
        c = sample.camera
        fid = sample.device_frame_id
        if fid >= 0:
            last = self.last_id[c]
            if last >= 0 and fid > last + 1:
                self.frame_gaps[c] += fid - last - 1
            self.last_id[c] = fid
        clock = self.clocks[c]
        if sample.device_time_ns >= 0:
            clock.kind = "device time"
            t = clock.capture_ns(sample.device_time_ns, sample.arrival_ns)
        elif fid >= 0:
            clock.kind = "frame id"
            t = clock.capture_ns(round(fid * self.period_ns), sample.arrival_ns)
        else:
            return sample.t_ns
        return t if clock.settled else None

    def push(self, sample: CameraSample) -> None:
        with self.cond:
            self._push(sample)

    def push_many(self, samples) -> None:
        """Several cameras' samples at once (a node's frames of one trigger): the lock
        taken and the frame loop woken once, not once per camera."""
        with self.cond:
            for sample in samples:
                self._push(sample)

    def _push(self, sample: CameraSample) -> None:
        """push, the lock held."""
        t = self.capture_ns(sample)
        if t is None:
            self.settling += 1
            return
        sample.t_ns = t
        if self.mode == "greedy":
            hist = self.latest[sample.camera]
            hist.append(sample)
            del hist[:-3]
            self._put(self._greedy_set(sample))
            return
        if self.last_t is not None and t < self.last_t + self.tol_ns:
            self.late += 1
            return
        group = None
        for g in self.pending:  # a few at most: the instants still being gathered
            if abs(t - g.t_ns) < self.tol_ns and sample.camera not in g.samples:
                group = g
                break
        if group is None:
            # which cameras this set waits for: asked once per set, not per sample
            # (eight threads push in turn; every microsecond here is latency)
            group = _Group(float(t), 0.0, {}, sample.arrival_ns,
                           set(np.flatnonzero(self.connected()).tolist()))
            k = len(self.pending)
            while k and self.pending[k - 1].t_ns > t:
                k -= 1
            self.pending.insert(k, group)
        group.samples[sample.camera] = sample
        group.waiting.discard(sample.camera)
        group.total_ns += t
        group.t_ns = group.total_ns / len(group.samples)
        if not group.waiting or len(group.samples) == self.n:
            self._emit(group)

    def _put(self, fs: FrameSet) -> None:
        if len(self.ready) == self.ready.maxlen:
            self.overflow += 1
        self.ready.append(fs)
        self._made.append(time.monotonic_ns())
        self.cond.notify()

    def _emit(self, group: _Group) -> None:
        # the sets before this one will never complete now
        while self.pending:
            g = self.pending.pop(0)
            self._emit_group(g)
            if g is group:
                return

    def _emit_group(self, group: _Group) -> None:
        samples = [group.samples[c] for c in sorted(group.samples)]
        ts = sorted(s.t_ns for s in samples)
        t = (ts[(len(ts) - 1) // 2] + ts[len(ts) // 2]) // 2  # the median capture time
        if self.last_t is not None and t < self.last_t + self.tol_ns:
            self.late += len(samples)  # a set whose time fell back onto the last one's
            return
        self.last_index = self._number(t, 1)
        self.last_t = t
        if len(samples) == self.n:
            self._waits.append(time.monotonic_ns() - group.first_arrival)
            if len(self._waits) % DEADLINE_EVERY == 0 or len(self._waits) == 64:
                self._fit_deadline()
        if len(samples) < self.n:
            self.incomplete += 1
            got = np.zeros(self.n, dtype=bool)
            got[list(group.samples)] = True
            self.missing[~got] += 1
        self._put(FrameSet(self.last_index, t, max(s.arrival_ns for s in samples), samples))

    def _fit_deadline(self) -> None:
        """The set deadline from the measured waits: their p99 plus a margin, never below
        the configured timeout nor above DEADLINE_MAX_FRAMES periods. A node's batch that
        usually lands 2 ms after the other nodes' is then waited for, not given up on;
        a camera that is truly gone still costs at most the bound."""
        p99 = float(np.percentile(np.fromiter(self._waits, np.float64), 99))
        top = max(self.base_timeout_ns, DEADLINE_MAX_FRAMES * self.period_ns)
        self.timeout_ns = int(min(max(p99 + DEADLINE_MARGIN_NS, self.base_timeout_ns), top))

    def _number(self, t: float, least_step: int) -> int:
        """The frame number of a set taken at t: frame periods since the origin (or since
        the first set), at least least_step past the last one (never back)."""
        if self.origin_ns is not None:
            number = round((t - self.origin_ns) / self.period_ns)
        elif self.last_t is None:
            number = 0
        else:
            number = self.last_index + round((t - self.last_t) / self.period_ns)
        return number if self.last_t is None else max(number, self.last_index + least_step)

    def _expire(self, now_ns: int) -> None:
        for g in list(self.pending):
            if g in self.pending and now_ns - g.first_arrival >= self.timeout_ns:
                self._emit(g)

    def _greedy_set(self, newest: CameraSample) -> FrameSet:
        """Every camera's latest blobs, moved to the newest sample's time along their 2D
        velocity (see blob_velocity). Sets of the same instant share a frame number."""
        t = newest.t_ns
        number = self._number(t, 0)
        if number > self.last_index or self.last_t is None:
            self.last_t, self.last_index = t, number
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
            out.append(CameraSample(cur.camera, cur.index, t, cur.arrival_ns, uv, cur.area,
                                    cur.peak, cur.device_time_ns, cur.device_frame_id))
        return FrameSet(self.last_index, t, newest.arrival_ns, out)

    @staticmethod
    def _rate_hz(times: deque) -> float | None:
        """Events a second over the times kept; None until they span a quarter second (at
        start-up a burst of sets made within microseconds would read as 40,000 a second)."""
        if len(times) < 2 or times[-1] - times[0] < 250_000_000:
            return None
        return (len(times) - 1) * 1e9 / (times[-1] - times[0])

    def _say_behind(self, now_ns: int) -> None:
        """The frame loop dropped sets to stay live: said with the measured rates (the
        lock held). Whole sets are dropped, the oldest waiting, so the sets kept are
        spread over time as the loop's pace allows, never a set missing cameras."""
        self._skip_ns = now_ns
        taken, made = self._rate_hz(self._taken), self._rate_hz(self._made)
        pace = (f"it takes {taken:.0f} frame sets a second of the {made:.0f} made"
                if taken is not None and made is not None
                else "its rate is not measured yet (it has just started)")
        self._behind = (f"the frame loop is behind: {pace}; the oldest waiting are skipped "
                        f"whole ({self.skipped} so far)")
        # logged once the rates are measured (a quarter second in): the line says how far
        if taken is not None and made is not None and now_ns - self._said_ns >= BEHIND_SAY_S * 1e9:
            self._said_ns = now_ns
            log.warning("%s", self._behind)

    @property
    def behind(self) -> str:
        """What the status says while the frame loop skips sets ("" when it keeps up)."""
        if time.monotonic_ns() - self._skip_ns > BEHIND_SHOWN_S * 1e9:
            return ""
        return self._behind

    def camera_status(self, camera: int) -> dict:
        """What the multiplexer knows of one camera: its clock against the daemon's and the
        frames its own counter skipped (taken but never delivered)."""
        return {"clock": self.clocks[camera].status(),
                "frame_gaps": int(self.frame_gaps[camera]),
                "sets_without": int(self.missing[camera]),  # given up on at the deadline
                "set_deadline_ms": self.timeout_ns * 1e-6}

    def next(self, timeout_s: float = 0.2) -> FrameSet | None:
        """The next frame set, or None after timeout_s with nothing to give."""
        deadline = time.monotonic_ns() + int(timeout_s * 1e9)
        with self.cond:
            while True:
                if self.ready:
                    skipped = 0
                    while len(self.ready) > self.max_backlog:
                        self.ready.popleft()
                        skipped += 1
                    now = time.monotonic_ns()
                    self._taken.append(now)
                    if skipped:
                        self.skipped += skipped
                        self._say_behind(now)
                    return self.ready.popleft()
                now = time.monotonic_ns()
                if self.pending:
                    self._expire(now)
                    if self.ready:
                        continue
                if now >= deadline:
                    return None
                wait = deadline - now
                if self.pending:
                    first = min(g.first_arrival for g in self.pending)
                    wait = min(wait, first + self.timeout_ns - now)
                self.cond.wait(max(wait, 0) * 1e-9 + 1e-5)
