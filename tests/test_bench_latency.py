"""benchmarks/bench_latency.py's steady figures: the rate from the packets' own span, the
frames missing between their numbers, the daemon's CPU per frame from /proc."""

import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "benchmarks"))
from bench_latency import steady_figures  # noqa: E402
from proc_cpu import process_cpu_s  # noqa: E402


def test_rate_missing_frames_and_cpu_per_frame_after_the_start():
    fps, skip = 240.0, 240
    frames = np.arange(3000)
    frames = frames[(frames != 1500) & (frames != 1501) & (frames != 2000)]  # 3 never sent
    # a slow start (the first second's packets spread over 3 s), then one every period
    arrival = np.where(frames < skip, frames * 3.0 / fps, 2.0 + frames / fps) * 1e9
    cpu = [(n, 0.5 + 0.0004 * n) for n in range(skip, len(frames), skip)]  # 0.4 ms a frame
    got = {"arrival": arrival.astype(np.int64).tolist(), "frames": frames.tolist(), "cpu": cpu}
    fig = steady_figures(got, skip)
    assert fig["rate_hz"] == pytest.approx(fps * (len(frames) - skip - 1)
                                           / (frames[-1] - frames[skip]), rel=1e-6)
    assert 239 < fig["rate_hz"] < 240  # the start's 3 s are not in it
    assert fig["frames_missing"] == 3
    assert fig["cpu_ms_per_frame"] == pytest.approx(0.4)


def test_process_cpu_grows_with_work_and_is_none_once_gone():
    child = subprocess.Popen([sys.executable, "-c",
                              "import time\nend = time.process_time() + 0.3\n"
                              "while time.process_time() < end: pass\ntime.sleep(60)"])
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and (process_cpu_s(child.pid) or 0) < 0.25:
            time.sleep(0.05)
        assert process_cpu_s(child.pid) >= 0.25
    finally:
        child.kill()
        child.wait()
    assert process_cpu_s(child.pid) is None
