"""The daemon's side of the live view: keep the newest frame, hand it to the view process.

Tracking never waits for the view. The per-frame hook only stores a reference to the
result (no copy, no lock); a feeder thread wakes FEED_HZ times a second, packs the newest
result into a few small arrays and sends them down a pipe to the view process, which does
everything else (the web server, thumbnails, the 3D scene) under its own interpreter
lock. A slow view blocks the feeder on the pipe, never the frame loop, and the frames in
between are dropped for the view: the queue is the one newest result.

A view process that ends (killed, out of memory, a bug in the web server) takes nothing
of tracking with it, and it comes back: the feed thread notices (its pipe breaks, or the
process is no longer alive), and its supervisor starts a new process on the same address
and hands it the rig again, with a back-off while that fails (the port still taken).
`mocapd status` shows the process (`view`: alive, restarts, how the last one ended).
"""

from __future__ import annotations

import ipaddress
import logging
import multiprocessing as mp
import socket
import threading
import time

import numpy as np

from calibkit.core.errors import UserError
from daemon.process.supervise import Supervised

log = logging.getLogger("mocapd.view")
FEED_HZ = 30.0  # frames a second the view gets (its 3D view redraws at this rate)
READY_TIMEOUT_S = 20.0  # the view process importing viser and binding its port
RESTART_MAX_WAIT_S = 30.0  # the back-off's ceiling between attempts to restart the view


class ViewEnded(RuntimeError):
    """The view process has ended while the daemon runs (its supervisor starts another)."""


def next_due(due: float, period: float, now: float) -> float:
    """The next deadline of a loop run `1 / period` times a second: one period after the
    last deadline (sleeping a period after the work would lose the work's time every
    round), but never more than half a period in the past (a stall is not caught up)."""
    return max(due + period, now - 0.5 * period)


def is_loopback(host: str) -> bool:
    return ipaddress.ip_address(host).is_loopback


def check_port_free(host: str, port: int) -> None:
    """A port in use is the user's to change: one line, before anything starts."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind((host, port))
        except OSError as exc:
            raise UserError(f"--view: cannot serve on {host}:{port}: {exc.strerror or exc}; "
                            "choose another port") from None


def pack(result) -> dict:
    """What the view needs of one frame, as small arrays (pickled down the pipe)."""
    tr, po = result.tracks, result.poses
    cams = [(int(s.camera), np.asarray(s.uv, np.float32), np.asarray(s.area, np.float32))
            for s in (result.samples or ())]
    out = {"frame": int(result.frame), "t_ns": int(result.t_ns),
           "latency_ms": (result.done_ns - result.arrival_ns) * 1e-6, "cameras": cams,
           "track_ids": tr.ids.copy(), "track_xyz": tr.xyz.astype(np.float32),
           "track_seen": tr.seen.copy(), "track_held": result.held_by_bodies(),
           "track_body": held_by(tr.ids, po.tracks),
           "body_ids": po.ids.copy(), "body_valid": po.valid.copy(),
           "body_position": po.position.astype(np.float32),
           "body_quaternion": po.quaternion.astype(np.float32)}
    lab = result.labelled
    if lab is not None and hasattr(lab, "index"):
        out["labelled_index"] = np.asarray(lab.index, np.int64)
        out["labelled_xyz"] = np.asarray(lab.xyz, np.float32)
    return out


def held_by(track_ids: np.ndarray, body_tracks: np.ndarray) -> np.ndarray:
    """(T,) the row of the body holding each track this frame, -1 for none (a body's
    markers are drawn in its colour)."""
    out = np.full(len(track_ids), -1, np.int64)
    bt = np.asarray(body_tracks).reshape(len(body_tracks), -1) if len(body_tracks) else \
        np.zeros((0, 0), np.int64)
    rows, _ = np.nonzero(bt >= 0)
    taken = bt[bt >= 0]
    if len(taken) and len(track_ids):
        order = np.argsort(track_ids)
        k = np.searchsorted(track_ids, taken, sorter=order)
        k = np.minimum(k, len(track_ids) - 1)
        hit = track_ids[order[k]] == taken
        out[order[k[hit]]] = rows[hit]
    return out


def describe(daemon) -> dict:
    """What the view needs once (and again after a reload): the rig, the bodies' names,
    where the control socket and the configuration are, the cameras' detection settings."""
    # deferred on purpose: loads numba (compiled kernels) only where used
    from daemon.config.mocapd import default_runtime_dir

    cfg = daemon.config
    ms = daemon._markerset() if hasattr(daemon, "_markerset") else None
    sticks = segment_of = None
    if ms is not None:
        # deferred on purpose: loads OpenCV only where used
        from daemon.view.draw import markerset_segments, markerset_sticks

        sticks = markerset_sticks(ms)
        segment_of = markerset_segments(ms)
    return {"rig": daemon.rig,
            "bodies": [(int(b.id), b.name) for b in daemon.pipeline.rigid.bodies],
            "runtime_dir": str(cfg.runtime_dir or default_runtime_dir()),
            "config": None if cfg.path is None else str(cfg.path),
            "cameras": {c.name: {"threshold": c.threshold, "min_area": c.min_area,
                                 "max_area": c.max_area,
                                 "mask": None if c.mask is None else str(c.mask)}
                        for c in cfg.cameras},
            "simulated": cfg.sim is not None, "sticks": sticks, "segment_of": segment_of,
            "fps": cfg.sim.fps if cfg.sim is not None else cfg.fps}


def _mask_times(cameras) -> tuple:
    """When each camera's mask file last changed: a mask redrawn under the same name is a
    change the view shows too."""
    out = []
    for c in cameras:
        try:
            out.append(c.mask.stat().st_mtime_ns if c.mask is not None else 0)
        except OSError:
            out.append(-1)
    return tuple(out)


class ViewLink:
    """The view process, started early (it imports the web server while the daemon sets
    up), then attached to the daemon's pipeline."""

    def __init__(self, host: str, port: int) -> None:
        check_port_free(host, port)
        self.host, self.port = host, port
        self._lock = threading.Lock()  # the process and its pipe are swapped under it
        self._latest = None
        self._stop = threading.Event()
        self._thread = None  # the feed (daemon.process.supervise.Supervised)
        self.supervised: list = []
        self._described: tuple | None = None
        self.sent = 0
        self.restarts = 0  # view processes started after the first one ended
        self.last_exit = None  # how the last one ended (its exit code; -N: signal N)
        self._lost = False  # the feed found the process ended: the next reset replaces it
        self._said_restart = -1e18  # when a restart was last logged
        self.url = f"http://{host if ':' not in host else f'[{host}]'}:{port}"
        self._spawn()

    def _spawn(self) -> None:
        """Start a view process and its pipe (it says ready, or why not, down the pipe)."""
        # deferred on purpose: loads OpenCV only where used
        from daemon.view.app import main

        ctx = mp.get_context("spawn")  # a fresh interpreter: nothing of the daemon's state
        self._conn, child = ctx.Pipe()
        self.process = ctx.Process(target=main, args=(child, self.host, self.port),
                                   name="mocapd-view", daemon=True)
        self.process.start()
        child.close()

    def status(self) -> dict:
        """The view process for `mocapd status`: where, alive, restarts, the last exit."""
        return {"url": self.url, "alive": bool(self.process.is_alive()),
                "pid": self.process.pid, "restarts": self.restarts,
                "last_exit": self.last_exit}

    def submit(self, result) -> None:
        """The per-frame hook: the newest result replaces the one before, nothing else."""
        self._latest = result

    def attach(self, daemon) -> None:
        """Wait for the view to serve (a failure is the user's: one line), give it the rig
        and hook it to the frame loop."""
        msg = self._conn.recv() if self._conn.poll(READY_TIMEOUT_S) else {
            "error": "the view process did not start (see the log)"}
        if "error" in msg:
            self.close()
            raise UserError(f"--view: {msg['error']}")
        self._daemon = daemon
        self._send({"setup": describe(daemon)})
        daemon.pipeline.hooks.append(self.submit)
        self._thread = Supervised("view-feed", self._feed, stopping=self._stop.is_set,
                                  reset=self._respawn, max_wait_s=RESTART_MAX_WAIT_S,
                                  expected=(ViewEnded,)).start()
        self.supervised = [self._thread]
        where = "" if is_loopback(self.host) else " (not loopback: anyone who can reach " \
                                                   "this address can see and change the rig)"
        log.info("live view at %s%s", self.url, where)

    def _send(self, obj) -> bool:
        """Send to the view; False once the process has ended (the feed then says so)."""
        try:
            self._conn.send(obj)
            return True
        except (BrokenPipeError, ConnectionResetError, OSError, EOFError):
            return False

    def _ended(self) -> ViewEnded:
        """The view process has ended (or no longer reads its pipe): the feed's failure."""
        self._lost = True
        self.process.join(1.0)  # a broken pipe comes a moment before the exit code
        self.last_exit = self.process.exitcode
        how = ("still running, its pipe broken" if self.last_exit is None
               else f"exit code {self.last_exit}")
        return ViewEnded(f"the live view process has ended ({how}); tracking goes on, "
                         "the view is restarted")

    def _respawn(self) -> None:
        """The supervisor's reset: a new view process in place of one that ended, given the
        rig again. A failure (the port still taken, no ready) raises: counted, and tried
        again after the back-off. A feed that failed with its process alive keeps it."""
        if not self._lost:
            return
        with self._lock:
            if self._stop.is_set():
                return
            if self.process.is_alive():
                self.process.terminate()
                self.process.join(2.0)
            self._conn.close()
            self._spawn()
        deadline = time.monotonic() + READY_TIMEOUT_S
        while not self._conn.poll(0.1):
            if self._stop.is_set():
                return
            if time.monotonic() > deadline or not self.process.is_alive():
                raise ViewEnded("a new view process did not start (see the log)")
        msg = self._conn.recv()
        if "error" in msg:
            raise ViewEnded(f"a new view process did not start: {msg['error']}")
        self._described = None  # the feed sends the rig first
        self._lost = False
        self.restarts += 1
        now = time.monotonic()
        if now - self._said_restart >= 60.0:  # a view killed over and over: a line a minute
            self._said_restart = now
            log.warning("live view restarted at %s (%d restarts so far)", self.url,
                        self.restarts)

    def _feed(self) -> None:
        period = 1.0 / FEED_HZ
        last = None
        due = time.monotonic()
        while True:
            due = next_due(due, period, time.monotonic())
            if self._stop.wait(max(0.0, due - time.monotonic())):
                return
            d = self._daemon
            key = (tuple(b.name for b in d.pipeline.rigid.bodies), str(d.config.path),
                   d.config.cameras, _mask_times(d.config.cameras))
            if key != self._described:  # a reload changed bodies or detection: tell the view
                self._described = key
                if not self._send({"setup": describe(d)}):
                    raise self._ended()
            res = self._latest
            if res is None or res is last:
                if not self.process.is_alive():  # no frame to send, and no one to send it
                    raise self._ended()
                continue
            last = res
            t0 = time.perf_counter()
            if not self._send({"frame": pack(res)}):
                raise self._ended()
            self.sent += 1
            if time.perf_counter() - t0 > 0.5:
                log.debug("the view took %.1f s to take a frame", time.perf_counter() - t0)

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(1.0)
        with self._lock:  # a restart under way has its process in place, or none
            self._close_process()

    def _close_process(self) -> None:
        if self._thread is None or not self._thread.is_alive():  # else stuck on a full pipe
            try:
                self._conn.send({"stop": True})
            except (OSError, EOFError, BrokenPipeError):
                pass
        self.process.join(3.0)
        if self.process.is_alive():
            self.process.terminate()
            self.process.join(2.0)
        self._conn.close()
