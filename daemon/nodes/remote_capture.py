"""A camera served by a node, as the daemon sees it: RemoteCapture, in the shape of a local
capture thread, fed by the hub (daemon/nodes/remote.py) with each of its node's samples.

Apart from the hub, which holds the Zenoh session and the nodes: this is one camera's
session, its lateness checks and its watchdog.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from typing import TYPE_CHECKING

from daemon.capture.sources import CameraSample

if TYPE_CHECKING:
    from daemon.nodes.remote import NodeHub, _Node

log = logging.getLogger("mocapd.nodes")


class _HubAlive:
    """What the frame loop asks of a capture's thread: alive while the hub runs."""

    def __init__(self, hub: NodeHub) -> None:
        self.hub = hub

    def is_alive(self) -> bool:
        return not self.hub._stop.is_set()


class RemoteCapture:
    """A camera served by a node, in the daemon's capture-thread shape (see the module).

    It has no thread of its own: a second thread per camera, woken for every frame, cost
    the daemon's interpreter as much as the rest of a sample's way and added its wake-up
    to every frame's latency. Zenoh's callback hands each sample to the multiplexer
    itself, and the hub's watchdog drops a camera that has gone silent. To the daemon it
    looks like daemon.capture.pipeline.CaptureThread: `push` and `on_open` (called before the
    first sample of every session, so the multiplexer starts the camera's clock afresh),
    `connected`, `frames`, `failures`, `rate_hz()`."""

    def __init__(self, hub: NodeHub, key: str) -> None:
        self.hub, self.key = hub, key
        self.cam = hub.cameras[key]
        self.name, self.camera = self.cam.name, self.cam.index
        self.source = self  # the daemon finds a capture's camera as capture.source.camera
        self.thread = _HubAlive(hub)
        self.timeout_ns = int(hub.settings.timeout_ms * 1e6)
        self.max_lag_ns = int(hub.settings.max_lag_ms * 1e6)
        self.push = None
        self.on_open = None
        self.connected = False
        self.frames = 0
        self.failures = 0
        self.last_error = ""
        self.times: deque = deque(maxlen=256)
        self._boot: int | None = None  # the node process of the current session
        self._last_good = 0
        self._lock = threading.Lock()

    # ---- the capture-thread interface ---------------------------------------------------------

    def start(self) -> None:
        self.cam.capture = self

    def stop(self) -> None:
        self.cam.capture = None

    def join(self, timeout: float = 1.0) -> None:
        pass

    def rate_hz(self) -> float:
        t = list(self.times)
        if len(t) < 2 or time.monotonic_ns() - t[-1] > 1e9:
            return 0.0
        return (len(t) - 1) / max((t[-1] - t[0]) * 1e-9, 1e-9)

    # ---- driven by the hub --------------------------------------------------------------------

    def deliver(self, s: CameraSample, node: _Node, has: int) -> None:
        """One sample the daemon has had since `has`, on Zenoh's thread: to the multiplexer
        unless late."""
        if self.accept(s, node, has):
            self.push(s)

    def accept(self, s: CameraSample, node: _Node, has: int) -> bool:
        """The checks and counts of deliver, without the push: whether `s` goes on to the
        multiplexer (the hub pushes a node's accepted samples together)."""
        lag = has - s.arrival_ns
        node.lag_ns = lag
        with self._lock:
            if self._boot is not None and node.boot != self._boot:
                self._drop(f"node {node.name} restarted")
            if lag > self.max_lag_ns:
                node.late += 1
                self.last_error = f"{node.name} is {lag * 1e-6:.0f} ms behind"
                return False
            if self._boot is None:  # a new session: the camera's clock starts again
                self._boot = node.boot
                self.cam.node, self.cam.boot = node.name, node.boot
                if self.on_open is not None:
                    self.on_open(self.camera)
                if self.failures:
                    log.warning("%s: reconnected (%s)", self.name, node.name)
            self.connected = True
            self._last_good = has
            self.frames += 1
            self.times.append(s.arrival_ns)
        return True

    def check(self, now_ns: int) -> None:
        """The watchdog: a camera with nothing on time for timeout_ms is dropped."""
        with self._lock:
            if self.connected and now_ns - self._last_good >= self.timeout_ns:
                late = self.last_error if "behind" in self.last_error else ""
                self._drop(late or f"no blobs from {self.cam.node or 'its node'} for "
                                   f"{(now_ns - self._last_good) * 1e-6:.0f} ms")

    def _drop(self, why: str) -> None:
        if self.connected:
            log.warning("%s: %s; dropped until it delivers again", self.name, why)
            self.failures += 1
        self.connected = False
        self.last_error = why
        self._boot = None
