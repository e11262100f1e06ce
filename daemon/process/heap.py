"""The collector kept off what the daemon builds before it starts tracking.

Why: Python's cycle collector, on its full (oldest-generation) passes, walks every object
the process holds: the simulated scene, the rig, the trackers, numba's and numpy's
modules. On the daemon that took 40-70 ms with the interpreter's lock held, every few
seconds to minutes, and every thread (capture, Zenoh, the frame loop) stopped for it: 15
frames at 240 fps with nothing tracked. What exists at the start is kept for the run
anyway, so it is collected once and frozen (`gc.freeze`: moved where the collector never
looks); the passes then walk only what the run itself makes. An in-process run (a test)
gives it back to the collector when it ends.
"""

from __future__ import annotations

import gc


def freeze_startup() -> None:
    """Collect what starting up left, then keep the rest out of the collector's passes
    (call when set up, before the threads that track start)."""
    gc.collect()
    gc.freeze()


def release() -> None:
    """What freeze_startup kept goes back to the collector (a run in a process that goes
    on: tests, a notebook)."""
    gc.unfreeze()
