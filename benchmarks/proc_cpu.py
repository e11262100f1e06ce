"""A process's CPU time from /proc, for benchmarks that time a daemon they started.

Why here: bench_latency, bench_nodes and bench_first_pose each read it, and a child's
CPU is what predicts a slower machine where wall time only describes this one.
"""

from __future__ import annotations

import os
from pathlib import Path


def process_cpu_s(pid: int) -> float | None:
    """User + system CPU time of process `pid` so far, all its threads (None once gone)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rpartition(")")[2].split()
    except OSError:
        return None
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
