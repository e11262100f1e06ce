"""Time to the first pose of `mocapd start --sim` on a fresh install, with and without the
kernels built ahead (`mocapd build-kernels`).

A fresh install has no compiled kernels: numba compiles each the first time it runs and
caches it on disk. Each scenario here gets its own empty cache (NUMBA_CACHE_DIR, so the
checkout's own __pycache__ caches are neither used nor touched):

- cold: `mocapd start --sim` on the empty cache, timed from the process start to the
  first UDP packet holding a valid rigid-body pose (the bodies are defined live at the
  start, as `--sim` does, so that is included);
- build: `mocapd build-kernels` on another empty cache;
- built: `mocapd start --sim` on that cache, `--repeats` times (median, worst).

Beside each wall time, the CPU time the daemon had used by its first pose: on a shared
machine the wall time is that stretched by the load.

The target (DESIGN.md): first pose <= 2 s after start.

    python benchmarks/bench_first_pose.py [--repeats 3] [--json out.json]
"""

from __future__ import annotations

import argparse
import os
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from calibkit.clitools import print_table, write_json
from daemon.publish.packet import decode

sys.path.insert(0, str(Path(__file__).resolve().parent))  # its sibling, when imported
from proc_cpu import process_cpu_s as cpu_s  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def first_pose_s(cache: str, timeout_s: float = 600.0) -> tuple[float, float, float]:
    """(s to the first packet, s to the first valid pose, CPU s the daemon had used by
    then: on a busy machine the wall time is the CPU time stretched by the load) of
    `mocapd start --sim`."""
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.bind(("127.0.0.1", 0))
    rx.settimeout(0.05)
    port = rx.getsockname()[1]
    env = {**os.environ, "NUMBA_CACHE_DIR": cache, "PYTHONPATH": str(ROOT)}
    began = time.monotonic()
    proc = subprocess.Popen([sys.executable, "-m", "daemon.cli", "start", "--sim", "--udp",
                             f"127.0.0.1:{port}", "--runtime-dir",
                             f"/tmp/mocapd-first-pose-{port}"],
                            cwd=ROOT, env=env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE)
    first = pose = None
    try:
        while pose is None and time.monotonic() - began < timeout_s:
            if proc.poll() is not None:
                raise SystemExit(f"mocapd exited: {proc.stderr.read().decode()[-500:]}")
            try:
                p = decode(rx.recv(65536))
            except TimeoutError:
                continue
            now = time.monotonic() - began
            first = first if first is not None else now
            if np.any(p.valid):
                pose, cpu = now, cpu_s(proc.pid)
    finally:
        proc.terminate()
        proc.communicate(timeout=30)
        rx.close()
    if pose is None:
        raise SystemExit(f"no pose within {timeout_s} s")
    return first, pose, cpu


def build_s(cache: str) -> float:
    env = {**os.environ, "NUMBA_CACHE_DIR": cache, "PYTHONPATH": str(ROOT)}
    began = time.monotonic()
    subprocess.run([sys.executable, "-m", "daemon.cli", "build-kernels", "--quiet"], cwd=ROOT,
                   env=env, check=True, capture_output=True)
    return time.monotonic() - began


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as cold, tempfile.TemporaryDirectory() as built:
        cold_first, cold_pose, cold_cpu = first_pose_s(cold)
        print(f"cold start: first pose after {cold_pose:.1f} s", file=sys.stderr, flush=True)
        build = build_s(built)
        print(f"build-kernels: {build:.1f} s", file=sys.stderr, flush=True)
        runs = [first_pose_s(built) for _ in range(args.repeats)]
    poses = [p for _, p, _ in runs]
    rows = [["cold (empty cache)", 1, round(cold_first, 2), round(cold_pose, 2),
             round(cold_cpu, 2), "-"],
            ["build-kernels", 1, "-", "-", "-", round(build, 1)],
            ["built ahead", args.repeats, round(float(np.median([r[0] for r in runs])), 2),
             round(float(np.median(poses)), 2), round(float(np.median([r[2] for r in runs])),
                                                      2), f"worst pose {max(poses):.2f}"]]
    print_table(rows, ["start", "runs", "first_packet_s", "first_pose_s", "cpu_s_to_pose",
                       "note"])
    print(f"load average at the end: {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
    if args.json:
        write_json(args.json, {"cold_first_packet_s": cold_first, "cold_first_pose_s": cold_pose,
                               "cold_cpu_s_to_pose": cold_cpu,
                               "build_kernels_s": build, "built_runs": runs,
                               "built_first_pose_s_median": float(np.median(poses)),
                               "built_first_pose_s_worst": max(poses)})


if __name__ == "__main__":
    main()
