"""What compiling costs `mocapd track`, and what `mocapd build-kernels` costs and saves.

On an empty NUMBA_CACHE_DIR of its own, each in a child process (wall time, and CPU time
and peak RSS from os.wait4): `mocapd track` on a cold cache (the baseline: it compiles
the tracking kernels and says so), then on another empty cache `mocapd build-kernels`,
then `mocapd track` --repeats times with the cache built, and the same with
--refine-bodies off (what the bodies' refinement adds). The take is bench_track's scene
(10 bodies of 4-5 markers, 120 Hz, hidden spans, 2 stray points a frame), --frames long.
The compile notices each run printed on stderr are counted.

    python benchmarks/bench_kernels.py [--frames 1668] [--repeats 3]
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import tomli_w

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_track import RATE, scene  # noqa: E402

from daemon.formats.c3dio import write_points_csv  # noqa: E402

NOTICE = "compiling the "


def _child(argv: list[str], cache: Path) -> tuple[float, float, float, int]:
    """(wall s, CPU s, peak RSS MB, compile notices) of one child process."""
    env = dict(os.environ, NUMBA_CACHE_DIR=str(cache))
    start = time.perf_counter()
    proc = subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=env)
    err = proc.stderr.read().decode(errors="replace")
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - start
    if os.waitstatus_to_exitcode(status) != 0:
        raise SystemExit(f"{' '.join(argv[:4])} ... failed: {err[-500:]}")
    return (wall, usage.ru_utime + usage.ru_stime, usage.ru_maxrss / 1024.0,
            err.count(NOTICE))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=1668)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="bench-kernels-"))
    pts, bodies, _ = scene(args.frames / RATE / 60.0)
    write_points_csv(tmp / "points.csv", pts)
    (tmp / "bodies.toml").write_text(tomli_w.dumps({"rigid_body": [
        {"name": b.name, "id": int(b.id), "markers": b.markers_body.tolist()}
        for b in bodies]}))
    mocapd = [sys.executable, "-m", "daemon.cli"]
    track = [*mocapd, "track", str(tmp / "points.csv"), "--bodies", str(tmp / "bodies.toml"),
             "--rate", f"{RATE:g}", "--out", str(tmp / "poses.csv")]
    rows = {"track, cold cache (baseline)": [_child(track, tmp / "cold")],
            "build-kernels": [_child([*mocapd, "build-kernels"], tmp / "built")]}
    rows["track, after build-kernels"] = [_child(track, tmp / "built")
                                          for _ in range(args.repeats)]
    rows["  the same, --refine-bodies off"] = [
        _child([*track, "--refine-bodies", "off"], tmp / "built") for _ in range(args.repeats)]
    shutil.rmtree(tmp)  # the take and both caches
    print(f"mocapd track on {args.frames} frames, 10 bodies; median (worst) of the runs; "
          f"load {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores at the end")
    print(f"{'what':>32s} | runs | {'wall s':>13s} | {'CPU s':>13s} | {'peak RSS MB':>11s} | "
          "compile notices")
    for name, runs in rows.items():
        r = np.array(runs)
        med, worst = np.median(r, axis=0), r.max(axis=0)
        print(f"{name:>32s} | {len(runs):4d} | {med[0]:6.1f} ({worst[0]:4.1f}) | "
              f"{med[1]:6.1f} ({worst[1]:4.1f}) | {med[2]:11.0f} | {int(r[:, 3].max())}")


if __name__ == "__main__":
    main()
