"""A capture node: opens its cameras, detects blobs and publishes them over Zenoh.

Each camera runs on a capture thread as in the daemon (daemon.capture.pipeline.CaptureThread: a
camera that fails is reopened), with the daemon's detector and per-camera settings
(daemon.capture.sources.DetectCamera). Each frame goes out alone on its camera's key as soon as it
is detected (CapturePublisher), stamped on the node's clock (daemon.publish.zenoh_wire); with
`publish = "sets"` the frames of one trigger from all the node's cameras go out as one
message when the last of them is in (SetPublisher). The node answers the daemon's clock
pings and announces its cameras once a second. Publishing never blocks: a message the link
cannot take is dropped (Zenoh's CongestionControl.DROP), so a slow link costs frames,
never the cameras' pace.

With `--sim` the node serves cameras of the simulated rig (daemon.synthetic.node_sim), on
a clock (NodeTime) that can be given an offset and a drift against the machine's, so the
daemon's clock estimate has work to do.
"""

from __future__ import annotations

import json
import logging
import os
import random
import sys
import threading
import time

from calibkit.cameras import missing_plugins
from calibkit.core.blas import one_blas_thread
from calibkit.core.errors import UserError
from calibkit.vision.detect import DetectorConfig
from daemon.capture.pipeline import CaptureThread
from daemon.capture.sources import DetectCamera
from daemon.nodes.settings import NodeConfig
from daemon.process import heap
from daemon.process.realtime import raise_priority, restore_normal
from daemon.publish import zenoh_wire as wire
from daemon.publish.zenoh_session import announce_key, blobs_key, ping_key, pong_key, sets_key

log = logging.getLogger("mocapd.node")
ANNOUNCE_S = 1.0
STALE_NS = 100_000_000  # a camera with no frame for this long is not waited for


class NodeTime:
    """The node's clock: the machine's monotonic clock, or (--sim) that clock with an
    offset and a drift, as a second computer's would be."""

    def __init__(self, offset_ns: int = 0, drift_ppm: float = 0.0) -> None:
        self.offset_ns, self.rate = int(offset_ns), 1.0 + drift_ppm * 1e-6

    def of(self, mono_ns: int) -> int:
        """The node-clock time of machine time `mono_ns`."""
        if self.rate == 1.0:
            return mono_ns + self.offset_ns
        return round(mono_ns * self.rate) + self.offset_ns

    def now(self) -> int:
        return self.of(time.monotonic_ns())


def _publisher(session, key: str):
    # deferred on purpose: loads Zenoh only where used
    import zenoh

    return session.declare_publisher(key, express=True,
                                     congestion_control=zenoh.CongestionControl.DROP,
                                     priority=zenoh.Priority.INTERACTIVE_HIGH)


class SetPublisher:
    """Gathers the node's cameras' frames of one trigger into one message.

    Why: the daemon's interpreter wakes for every message it gets; 32 cameras at 240 fps
    sent one frame a message are 7680 wake-ups a second, most of the time a frame spends
    between node and daemon. A set goes out, on the capture thread of its last frame, as
    soon as every camera that is delivering has a frame in it. A camera whose frame has
    not come is waited for at most `wait_ns`: the set then goes without it (from a thread
    of its own, marked short), and the late frame, when it comes, goes out alone at once,
    as the rest of that set (by its capture time: within half its camera's frame period of
    the set's). A camera's next frame closes the set its last one is in; a camera with no
    frame for STALE_NS is not waited for. The daemon's multiplexer pairs frames by their
    capture times, so a split set costs a message, never a frame's time."""

    def __init__(self, session, key: str, boot: int, clock: NodeTime, names: list[str],
                 wait_ns: int) -> None:
        self.pub = _publisher(session, key)
        self.boot, self.clock, self.wait_ns = boot, clock, int(wait_ns)
        self.names = [n.encode("ascii") for n in names]
        self.last = [0] * len(names)  # each camera's latest frame came (machine clock, ns)
        self.last_t = [0] * len(names)  # and was taken (its t_ns)
        self.period = [0] * len(names)  # between its last two frames' t_ns
        self.pending: dict[int, object] = {}  # camera slot -> its sample in the open set
        self.expect: set[int] = set()
        self.opened = 0  # when the open set got its first frame (machine clock, ns)
        self.missed: tuple[int, set] = (0, set())  # the last short set: its time, who missed
        self.seq = 0
        self.sent = 0  # messages
        self.short = 0  # sets sent without a camera that was waited for
        self.cond = threading.Condition()
        self.closed = False
        self.timer = threading.Thread(target=self._time_out, name="set-timer", daemon=True)

    def start(self) -> None:
        self.timer.start()

    def close(self) -> None:
        with self.cond:
            self.closed = True
            self.cond.notify()

    def push_for(self, slot: int):
        """The capture thread's push for camera `slot`."""
        return lambda s: self.add(slot, s)

    def add(self, slot: int, s) -> None:
        now = time.monotonic_ns()
        with self.cond:
            self.last[slot] = now
            if self.last_t[slot]:
                self.period[slot] = s.t_ns - self.last_t[slot]
            self.last_t[slot] = s.t_ns
            t_set, missed = self.missed
            if slot in missed:
                missed.discard(slot)
                if 2 * abs(s.t_ns - t_set) < self.period[slot]:  # the short set's own
                    self._publish({slot: s}, short=False)
                    return
            if slot in self.pending:  # its next frame: the open set gets no more
                self._send()
            if not self.pending:
                self.opened = now
                self.expect = {i for i, t in enumerate(self.last) if now - t < STALE_NS}
                self.cond.notify()
            self.pending[slot] = s
            if len(self.pending) >= len(self.expect) and self.expect.issubset(self.pending):
                self._send()

    def _time_out(self) -> None:
        with self.cond:
            while not self.closed:
                if not self.pending:
                    self.cond.wait(0.5)
                    continue
                left = self.opened + self.wait_ns - time.monotonic_ns()
                if left > 0:
                    self.cond.wait(left * 1e-9)
                    continue
                self._send()

    def _send(self) -> None:
        """Publishes the open set (the lock held: sets leave in order)."""
        missing = self.expect.difference(self.pending)
        if missing:
            self.short += 1
            self.missed = (min(s.t_ns for s in self.pending.values()), missing)
        pending, self.pending = self.pending, {}
        self._publish(pending, short=bool(missing))

    def _publish(self, frames: dict, short: bool) -> None:
        of = self.clock.of
        rows = [(self.names[k], s.index, of(s.t_ns), of(s.arrival_ns), s.device_time_ns,
                 s.device_frame_id, s.uv, s.area, s.peak) for k, s in sorted(frames.items())]
        data = wire.encode_sets(self.boot, self.seq, self.clock.now(), rows,
                                wire.SET_SHORT if short else 0)
        self.seq += 1
        self.pub.put(data)
        self.sent += 1


class CapturePublisher:
    """Pushes one camera's samples out as blobs messages (called on its capture thread)."""

    def __init__(self, session, key: str, boot: int, clock: NodeTime) -> None:
        self.pub = _publisher(session, key)
        self.boot, self.clock = boot, clock
        self.seq = 0
        self.sent = 0

    def __call__(self, s) -> None:
        of = self.clock.of
        data = wire.encode_blobs(self.boot, self.seq, s.index, of(s.t_ns), of(s.arrival_ns),
                                 self.clock.now(), s.device_time_ns, s.device_frame_id, s.uv,
                                 s.area, s.peak)
        self.seq += 1
        self.pub.put(data)
        self.sent += 1


class Node:
    """The node's session, capture threads, clock answers and announcements."""

    def __init__(self, cfg: NodeConfig, sources, clock: NodeTime | None = None,
                 capture=None) -> None:
        """`capture(sources, pushes)`: what runs the cameras, as (runners with start, stop
        and join; per camera, a state with connected and frames); by default a capture
        thread each (daemon.capture.pipeline.CaptureThread), both roles in one."""
        self.cfg, self.sources = cfg, list(sources)
        self.capture = capture or _capture_threads
        self.clock = clock or NodeTime()
        self.boot = random.SystemRandom().getrandbits(32)
        self.scheduling = "normal"  # its threads' priority once started (daemon.process.realtime)
        self.stop_event = threading.Event()
        self.runners: list = []
        self.captures: list = []  # per camera: connected, frames
        self.sets: SetPublisher | None = None
        self.session = None
        self.pings = 0
        self._blas = None  # the BLAS thread limit while running (calibkit.core.blas)

    def _on_ping(self, sample) -> None:
        t2 = self.clock.now()
        try:
            seq, t1 = wire.decode_ping(sample.payload.to_bytes())
        except wire.WireError:
            return
        self.pings += 1
        self._pong.put(wire.encode_pong(self.boot, seq, t1, t2, self.clock.now()))

    def _announce(self) -> None:
        rig = self.cfg.session.rig
        self.session.put(announce_key(rig, self.cfg.name), json.dumps({
            "node": self.cfg.name, "boot": self.boot, "pid": os.getpid(),
            "scheduling": self.scheduling,
            "cameras": [s.name for s in self.sources],
            "connected": [c.connected for c in self.captures],
            "frames": [c.frames for c in self.captures]}))

    def start(self) -> None:
        # deferred on purpose: loads Zenoh only where used
        import zenoh

        # a clock ping waits for the interpreter's lock before it is stamped; the default
        # 5 ms switch interval would let a busy capture thread add that to one leg only
        sys.setswitchinterval(1e-4)
        # ahead of ordinary work, as the daemon's threads (daemon.process.realtime): before the
        # session and the capture threads start, so that theirs inherit it. Zenoh's threads,
        # the clock's answers and the set timer one step above the capture threads: a set
        # that is ready leaves at once even while other cameras' detection holds every core
        # (under SCHED_RR a thread of equal priority waits for the running one to block:
        # 4 publishers with a node's work on 2 cores: p99 0.75 -> 0.19 ms in benchmarks/
        # zenoh_floor.py, see docs/nodes.md)
        priority = self.cfg.realtime_priority
        self.scheduling = raise_priority(min(priority + 1, 99) if priority > 0 else 0)
        self._blas = one_blas_thread()  # as the daemon's (daemon.service.daemon.Daemon.run)

        rig = self.cfg.session.rig
        self.session = self.cfg.session.open()
        self._pong = self.session.declare_publisher(
            pong_key(rig, self.cfg.name), express=True,
            congestion_control=zenoh.CongestionControl.DROP,
            priority=zenoh.Priority.REAL_TIME)
        self._ping_sub = self.session.declare_subscriber(ping_key(rig), self._on_ping)
        if self.cfg.publish == "sets":
            self.sets = SetPublisher(self.session, sets_key(rig, self.cfg.name), self.boot,
                                     self.clock, [s.name for s in self.sources],
                                     round(self.cfg.set_wait_ms * 1e6))
            self.sets.start()
        if self.scheduling.startswith("SCHED_RR") and priority < 99:
            # a step down for this thread and the capture threads it starts next
            self.scheduling = raise_priority(priority) + f" (network {priority + 1})"
        pushes = [self.sets.push_for(k) if self.sets is not None else
                  CapturePublisher(self.session, blobs_key(rig, src.name), self.boot,
                                   self.clock) for k, src in enumerate(self.sources)]
        self.runners, self.captures = self.capture(self.sources, pushes)
        heap.freeze_startup()  # as the daemon does (daemon.process.heap)
        for runner in self.runners:
            runner.start()
        log.info("node %s (boot %08x): %d cameras on mocap/%s/ (%s)", self.cfg.name,
                 self.boot, len(self.sources), rig,
                 ", ".join(self.cfg.session.connect + self.cfg.session.listen))

    def run(self, duration_s: float | None = None) -> None:
        self.start()
        end = None if duration_s is None else time.monotonic() + duration_s
        try:
            while not self.stop_event.is_set():
                self._announce()
                wait = ANNOUNCE_S if end is None else min(ANNOUNCE_S, end - time.monotonic())
                if wait <= 0 or self.stop_event.wait(wait):
                    break
        finally:
            self.close()

    def close(self) -> None:
        for runner in self.runners:
            runner.stop()
        for runner in self.runners:
            runner.join(0.5)
        if self.sets is not None:
            self.sets.close()
        if self.session is not None:
            self.session.close()
            self.session = None
        restore_normal()
        heap.release()
        if self._blas is not None:
            self._blas.restore_original_limits()
            self._blas = None


def _capture_threads(sources, pushes):
    threads = [CaptureThread(src, push) for src, push in zip(sources, pushes, strict=True)]
    return threads, threads


def live_sources(cfg: NodeConfig):
    """The node's own cameras, with the daemon's detector and per-camera settings."""
    if not cfg.cameras:
        where = f"{cfg.path}: " if cfg.path else ""
        raise UserError(f"{where}camera: the node has no cameras; add [[camera]] tables or "
                        "use --sim")
    out = []
    for i, cam in enumerate(cfg.cameras):
        missing = missing_plugins([cam.source.partition(":")[0]])
        if missing:
            log.error("%s: skipped: plugin %s is not installed", cam.name, missing[0])
            continue
        det = DetectorConfig(threshold=cam.threshold, min_area=cam.min_area,
                             max_area=cam.max_area)
        out.append(DetectCamera(cam.name, i, cam.source, det, cam.fps,
                                device_stamps=cam.timestamps == "device"))
    if not out:
        raise UserError("no camera can be opened (see the messages above)")
    return out
