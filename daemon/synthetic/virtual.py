"""The simulated cameras run in virtual time: a capture as capture threads would make it,
faster than real time, with the same frames and the same truth.

Each camera paces itself by a clock of its own that only its sleeps advance; their samples
are merged in arrival order and pushed to a multiplexer, a camera that fails is reopened
after the capture thread's retry delay (its clock reset when it delivers again), and sets
are expired on their timeout as the frame loop would. Tests and benchmarks use it to run
minutes of capture in seconds and check each set against the scene's ledger.
"""

from __future__ import annotations

import heapq

import numpy as np

from daemon.capture.multiplexer import Multiplexer
from daemon.synthetic.scene import SimCamera, SimScene

START_NS = 10**12
GRACE_NS = 1_000_000_000  # as the service: sets wait this long for cameras not open yet


class VirtualClock:
    """A camera's own view of time, advanced only by its sleeps. `stalls`: (from, to)
    spells (ns) in which its capture thread does not run (a busy computer): whatever it
    would have done then, it does at the spell's end, so frames taken meanwhile arrive
    together, late."""

    def __init__(self, t_ns: int, stalls=()) -> None:
        self.t = t_ns
        self.stalls = list(stalls)

    def now(self) -> int:
        for start, end in self.stalls:
            if start <= self.t < end:
                return end
        return self.t

    def sleep(self, seconds: float) -> None:
        self.t = self.now() + round(seconds * 1e9)


def frame_sets(scene: SimScene, seconds: float | None = None, retry_s: float = 0.2,
               make_mux=Multiplexer, stalls=None, starts=None, on_mux=None):
    """Frame sets of every camera of `scene` as the multiplexer makes them, one at a time,
    for `seconds` of virtual time (None: until the caller stops). Each camera opens at its
    own moment, counts frames from its own start, stamps them on its own clock and loses
    the frames the scene drops; their samples are pushed in arrival order to
    `make_mux(n_cameras, mode, fps, timeout_frames, connected=..., origin_ns=...)`, which
    pairs them by capture time. `stalls`: per camera, (from, to) spells in ns from the
    start in which its capture thread does not run (VirtualClock). `starts`: a list that
    gets, per camera, the times it started delivering; `on_mux`: called with the
    multiplexer once made (its counters are the run's)."""
    n = len(scene.rig)
    stalls = stalls or {}
    clocks = [VirtualClock(START_NS, [(START_NS + a, START_NS + b) for a, b in
                                      stalls.get(c, ())]) for c in range(n)]
    cams = [SimCamera(scene, c, START_NS, clocks[c].now, clocks[c].sleep) for c in range(n)]
    gens = [cam.open() for cam in cams]
    live = np.zeros(n, dtype=bool)  # delivering in its current session
    delivered = np.zeros(n, dtype=bool)
    now = [START_NS]

    def connected():
        return live | (~delivered & (now[0] < START_NS + GRACE_NS))

    mux = make_mux(n, "triggered", scene.fps, 1.5, connected=connected, origin_ns=START_NS)
    if on_mux is not None:
        on_mux(mux)
    fresh = np.ones(n, dtype=bool)  # its next sample starts a session
    if starts is not None:
        starts[:] = [[] for _ in range(n)]

    def advance(c):
        while True:
            try:
                return next(gens[c])
            except OSError:
                live[c] = False
                clocks[c].sleep(retry_s)
                gens[c] = cams[c].open()
                fresh[c] = True

    heap = [(s.arrival_ns, c, s) for c in range(n) for s in [advance(c)]]
    heapq.heapify(heap)
    end = None if seconds is None else START_NS + round(seconds * 1e9)
    while heap and (end is None or heap[0][0] < end):
        t, c, s = heapq.heappop(heap)
        now[0] = t
        if fresh[c]:
            fresh[c] = False
            mux.reset_camera(c)
            if starts is not None:
                starts[c].append(t)
        live[c] = delivered[c] = True
        mux.push(s)
        if mux.pending:  # sets still gathering: the ones timed out go (as the frame loop's)
            with mux.cond:
                mux._expire(t)
        if mux.ready:
            ready = list(mux.ready)
            mux.ready.clear()
            yield from ready
        s = advance(c)
        heapq.heappush(heap, (s.arrival_ns, c, s))


def capture(scene: SimScene, seconds: float, retry_s: float = 0.2, make_mux=Multiplexer,
            stalls=None):
    """Every camera of `scene` for `seconds` of virtual time (frame_sets). Returns (sets,
    the multiplexer, per camera the times it started delivering)."""
    starts: list = []
    muxes: list = []
    sets = list(frame_sets(scene, seconds, retry_s, make_mux, stalls, starts, muxes.append))
    return sets, muxes[0], starts


def spread_ns(scene: SimScene, fs) -> int | None:
    """How far apart the set's cameras really took their frames (the ledger's truth); None
    if a sample is not in the ledger."""
    taken = [scene.taken_ns(s) for s in fs.samples]
    if None in taken:
        return None
    return max(taken) - min(taken)
