"""Stopping `mocapd start` (issue 30): SIGTERM ends the process with everything flushed.

The process ends without the interpreter's teardown once its work is written
(daemon/process/ending.py), so what must be written by then is checked here: the exit code,
the recording whole (the daemon's last word on it, "N of M frames written", against the
file), the control socket removed, the figures printed and their JSON written. How long the
stop takes is measured by benchmarks/bench_stop.py, not here.
"""

from __future__ import annotations

import json
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

from calibkit.core.recording import load_observations

ROOT = Path(__file__).resolve().parents[1]
CLOSED = re.compile(r"recording closed, (\d+) of (\d+) frames written")


def _start(tmp_path: Path, *extra) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "daemon.cli", "start", "--sim",
                             "--sim-cameras", "3", "--sim-bodies", "1", "--sim-fps", "60",
                             "--runtime-dir", str(tmp_path / "rt"), *map(str, extra)],
                            cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)


def test_sigterm_leaves_the_recording_whole_and_the_figures_written(tmp_path):
    from daemon.service.control import request

    rt = tmp_path / "rt"
    take = tmp_path / "take.mcrec"
    proc = _start(tmp_path, "--json", tmp_path / "run.json")
    try:
        deadline = time.monotonic() + 300
        while True:
            try:
                if request(rt, {"cmd": "status"}, timeout_s=10.0).get("frames", 0) > 0:
                    break
            except Exception:  # noqa: BLE001 - not up yet
                pass
            assert proc.poll() is None and time.monotonic() < deadline, "mocapd did not start"
            time.sleep(0.1)
        assert request(rt, {"cmd": "record", "path": str(take)})["ok"]
        deadline = time.monotonic() + 120
        while (request(rt, {"cmd": "status"}).get("recording_status") or {}).get("sent", 0) < 5:
            assert time.monotonic() < deadline, "nothing recorded"
            time.sleep(0.05)
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, err
    said = CLOSED.findall(err)
    assert len(said) == 1, err
    written, handed = map(int, said[0])
    assert written == handed >= 5
    assert len(load_observations(take)[0].frames()) == written
    assert not (rt / "mocapd.sock").exists()
    figures = json.loads((tmp_path / "run.json").read_text())
    assert figures["frames"] > 0 and "frames" in out  # the table printed, then flushed


def test_a_run_to_its_end_prints_and_writes_its_figures(tmp_path):
    proc = _start(tmp_path, "--frames", 40, "--json", tmp_path / "run.json")
    out, err = proc.communicate(timeout=300)
    assert proc.returncode == 0, err
    assert json.loads((tmp_path / "run.json").read_text())["frames"] == 40
    assert re.search(r"^frames\s+40\b", out, re.MULTILINE), out
