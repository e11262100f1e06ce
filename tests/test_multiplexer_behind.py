"""A frame loop that cannot keep up is told about and degrades by design: whole frame
sets are skipped (never a set missing cameras), with a warning giving the measured rates."""

from __future__ import annotations

import logging
import threading
import time

import numpy as np

from daemon.capture.multiplexer import Multiplexer
from daemon.capture.sources import CameraSample

CAMERAS = 4
SETS = 400


def _sample(camera: int, k: int, t0: int, period_ns: float) -> CameraSample:
    t = t0 + round(k * period_ns)
    uv = np.array([[100.0 + camera, 200.0 + k]])
    return CameraSample(camera, k, t, t + 500_000, uv, np.ones(1), np.full(1, 200.0))


def test_a_slow_frame_loop_skips_whole_sets_and_says_so(caplog):
    mux = Multiplexer(CAMERAS, fps=240.0)
    assert mux.behind == ""
    t0 = time.monotonic_ns()
    done = threading.Event()

    def cameras():
        for k in range(SETS):
            mux.push_many([_sample(c, k, t0, mux.period_ns) for c in range(CAMERAS)])
            time.sleep(0.001)
        done.set()

    taken = []
    thread = threading.Thread(target=cameras, daemon=True)
    with caplog.at_level(logging.WARNING, logger="mocapd.multiplexer"):
        thread.start()
        deadline = time.monotonic() + 120.0
        while time.monotonic() < deadline:
            fs = mux.next(0.2)
            if fs is None:
                if done.is_set():
                    break
                continue
            taken.append(fs)
            time.sleep(0.01)  # the artificially slow stage: 10 ms a set
        thread.join(5.0)
    assert done.is_set() and taken
    assert mux.skipped > 0
    # every set the loop got is whole, with each camera's sample of that very instant
    for fs in taken:
        assert [s.camera for s in fs.samples] == list(range(CAMERAS))
        assert len({s.index for s in fs.samples}) == 1
    assert mux.incomplete == 0
    # nothing lost unaccounted: each made set was taken, or skipped (or, if the cameras
    # ran 64 sets ahead of a starved loop, overflowed: counted too)
    assert len(taken) + mux.skipped + mux.overflow == SETS
    indices = [fs.samples[0].index for fs in taken]
    assert indices == sorted(indices) and indices[-1] == SETS - 1
    said = [r.getMessage() for r in caplog.records if "frame loop is behind" in r.getMessage()]
    assert len(said) == 1, said  # rate-limited: one line for the whole run
    assert "frame sets a second" in said[0] and "skipped whole" in said[0]
    assert "frame loop is behind" in mux.behind


def test_a_frame_loop_that_keeps_up_is_not_said_to_be_behind(caplog):
    mux = Multiplexer(CAMERAS, fps=240.0)
    t0 = time.monotonic_ns()
    with caplog.at_level(logging.WARNING, logger="mocapd.multiplexer"):
        for k in range(50):
            mux.push_many([_sample(c, k, t0, mux.period_ns) for c in range(CAMERAS)])
            fs = mux.next(5.0)
            assert fs is not None and len(fs.samples) == CAMERAS
    assert mux.skipped == 0 and mux.behind == ""
    assert not [r for r in caplog.records if "behind" in r.getMessage()]
