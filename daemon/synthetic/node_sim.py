"""The simulated cameras a capture node serves with `mocapd node --sim`.

The same scene, seed and cameras as the daemon's [sim] makes (at its default length, which
shapes the motion), taken on one trigger grid with trigger 0 at the machine's monotonic
zero: nodes started at different moments on one machine, or in network namespaces on it,
still take their frames together, and a daemon with the same [sim] scores them against
the same truth. The truth (the scene's ledger) stays in the node's process. The cameras
are served from one thread (SimNodeCapture).
"""

from __future__ import annotations

import heapq
import logging
import time

from calibkit.core.errors import UserError
from daemon.capture.sources import fine_timer_slack
from daemon.nodes.settings import NodeConfig
from daemon.process.worker import Worker

log = logging.getLogger("mocapd.node")


def sim_sources(cfg: NodeConfig):
    """The simulated cameras this node serves, on the shared trigger grid."""
    # deferred on purpose: loads OpenCV only where used
    from daemon.synthetic.scene import SimCamera, SimScene

    if cfg.sim is None:
        raise UserError("--sim needs the simulated rig: a [sim] table in node.toml, or "
                        "--sim-cameras")
    scene = SimScene(cfg.sim)
    names = scene.rig.names
    serve = cfg.sim_cameras or tuple(names)
    unknown = [c for c in serve if c not in names]
    if unknown:
        raise UserError(f"node_sim.cameras: {', '.join(unknown)} not in the simulated rig "
                        f"({', '.join(names)})")
    return [SimCamera(scene, names.index(c), 0) for c in serve]


class _CameraState:
    """What the node reports of one camera served by SimNodeCapture (as a capture
    thread's: connected, frames)."""

    def __init__(self, name: str) -> None:
        self.name = name
        self.connected = False
        self.frames = 0
        self.failures = 0


class SimNodeCapture(Worker):
    """All of a simulated node's cameras on one thread.

    Why: a node stands for a computer of its own, but the nodes of a test or benchmark
    share this machine's cores with the daemon; a thread per simulated camera is a thread
    switch per frame (32 cameras at 240 fps: 7680 a second) that a real node would make
    on its own computer, and they queue ahead of the daemon's. One thread merges its
    cameras' sessions (SimCamera.session) by arrival time, sleeps until each frame is due
    and stamps its arrival when it wakes, as a camera's own thread would; frames already
    due when it wakes are taken at once. A camera that fails (simulated disconnection) is
    reopened after `retry_s`, as daemon.capture.pipeline.CaptureThread does."""

    def __init__(self, cameras, pushes, retry_s: float = 0.2) -> None:
        self.cameras, self.pushes = list(cameras), list(pushes)
        self.retry_ns = int(retry_s * 1e9)
        self.states = [_CameraState(c.name) for c in self.cameras]
        super().__init__("sim-cameras")

    def _open(self, heap: list, slot: int) -> None:
        session = self.cameras[slot].session()
        due, take = next(session)
        heapq.heappush(heap, (due, slot, take, session))

    def _run(self) -> None:
        fine_timer_slack()
        heap: list = []
        for slot in range(len(self.cameras)):
            self._open(heap, slot)
        while not self._stop.is_set():
            due, slot, take, session = heapq.heappop(heap)
            wait = due - time.monotonic_ns()
            if wait > 0:
                time.sleep(wait * 1e-9)
            if take is None:  # a failed camera's retry is due
                self._open(heap, slot)
                continue
            state = self.states[slot]
            try:
                sample = take(time.monotonic_ns())
            except OSError as exc:
                if state.connected:
                    log.warning("%s: %s; reopening", state.name, exc)
                state.connected = False
                state.failures += 1
                heapq.heappush(heap, (time.monotonic_ns() + self.retry_ns, slot, None, None))
                continue
            state.connected = True
            state.frames += 1
            self.pushes[slot](sample)
            due, take = next(session)
            heapq.heappush(heap, (due, slot, take, session))


def sim_capture(sources, pushes):
    """Node(capture=...) for simulated cameras: one SimNodeCapture for them all."""
    group = SimNodeCapture(sources, pushes)
    return [group], group.states
