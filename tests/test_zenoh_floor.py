"""benchmarks/zenoh_floor.py: its table on a short run, and bad arguments refused in one
line. The figures are the benchmark's, not asserted here (the suite asserts no speed)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "benchmarks" / "zenoh_floor.py"
ENV = dict(os.environ, PYTHONPATH=str(ROOT))


@pytest.mark.slow  # 4 configurations of subprocesses: about 16 s
def test_a_short_run_prints_every_row_with_its_figures():
    r = subprocess.run([sys.executable, str(SCRIPT), "--seconds", "0.5", "--repeats", "1"],
                       capture_output=True, text=True, env=ENV, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    rows = [line for line in r.stdout.splitlines() if line.startswith(("1 publisher",
                                                                      "4 publishers"))]
    assert len(rows) == 4
    for row in rows:
        cells = row.split()
        if "needs root" in row:  # the real-time rows on a machine that refuses them
            assert os.geteuid() != 0
            continue
        median, p90, p99 = (float(c) for c in cells[-4:-1])
        assert 0 < median <= p90 <= p99


def test_bad_arguments_are_one_line_and_exit_non_zero():
    r = subprocess.run([sys.executable, str(SCRIPT), "--seconds", "0"],
                       capture_output=True, text=True, env=ENV, timeout=60)
    assert r.returncode != 0
    assert r.stderr.strip().splitlines() == [
        "zenoh_floor: --seconds and --repeats must be positive, --work-ms >= 0"]
