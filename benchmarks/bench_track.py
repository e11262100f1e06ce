"""Speed of `mocapd track` (daemon.analysis.offline_track) on a long take of anonymous 3D markers.

Scene (calibkit.synthetic.sim.rigid_body_motion): 10 rigid bodies of 4 or 5 markers moving
through a 4 m room for --minutes at 120 Hz; 0.5 mm noise per axis, 5 % of marker-frames
hidden in spans of 0.1-1 s, 2 stray points a frame, points shuffled within each frame.
Rows, each timed as wall clock and as this process's CPU time (the machine may be shared:
CPU time is what the work costs), median and worst over --repeats:
  - identities: daemon.analysis.point_tracks.associate alone;
  - track: identities + the rigid tracker, steady runs fitted at once (what the command
    runs);
  - baseline, per frame: identities + RigidTracker.update() on every frame, the live
    loop (on the first --baseline-frames frames; frames/s compare);
  - end to end: `mocapd track` in this process, reading the points CSV and writing the
    poses CSV (once per repeat).
Pose errors against the truth are printed for the tracked take (every valid pose counted,
gross: > 20 mm or > 5 deg).

With --big-csv PATH (a file from benchmarks/gen_points_csv.py, its bodies beside it) it
measures instead, each in a child process of its own, wall time, CPU time and peak RSS
(the child's own, from os.wait4) of: reading the points CSV whole (c3dio.read_points_csv,
the reader `mocapd track` used before; the baseline), reading it streamed
(daemon/formats/points_csv.py), and the whole `mocapd track` command.

    python benchmarks/bench_track.py [--minutes 10] [--repeats 3] [--baseline-frames 6000]
    python benchmarks/gen_points_csv.py --mb 1000 --out /tmp/points_1g.csv
    python benchmarks/bench_track.py --big-csv /tmp/points_1g.csv --repeats 1
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import tomli_w

from calibkit.synthetic import sim
from daemon.analysis.offline_track import (
    MarkerCloud,
    cloud_from_points,
    rotation_difference_deg,
    track_cloud,
)
from daemon.analysis.point_tracks import associate
from daemon.formats.c3dio import Points, Take, write_points_csv
from daemon.synthetic.labelling import hide_spans
from daemon.tracking.rigid import BodyDef, quaternion_xyzw

RATE = 120.0


def scene(minutes: float, seed: int = 0):
    n = int(minutes * 60 * RATE)
    counts = [4, 5] * 5
    truth, bodies = sim.rigid_body_motion(10, n, fps=RATE, markers_per_body=counts, seed=seed)
    k = int(truth.marker.max()) + 1
    xyz = np.full((n, k, 3), np.nan)
    xyz[truth.frame, truth.marker] = truth.xyz
    take = hide_spans(Take([str(i) for i in range(k)], xyz, RATE), 0.05, seed=seed + 1)
    rng = np.random.default_rng(seed + 2)
    noisy = take.xyz_m + rng.normal(0.0, 0.0005, take.xyz_m.shape)
    pts = Points.from_take(Take(take.labels, noisy, RATE), seed=seed + 3)
    sf = np.repeat(np.arange(n), 2)
    sx = rng.uniform([-1.5, -1.5, 0.2], [1.5, 1.5, 2.0], (len(sf), 3))
    pts = Points(np.concatenate([pts.frame, sf]), np.concatenate([pts.xyz_m, sx]))
    defs = [BodyDef(b.name, b.id, b.markers_body, np.zeros(3), 4, 3, 0.0) for b in bodies]
    return pts, bodies, defs


def timed(fn):
    w, c = time.perf_counter(), time.process_time()
    out = fn()
    return out, time.perf_counter() - w, time.process_time() - c


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--minutes", type=float, default=10.0)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--baseline-frames", type=int, default=6000)
    parser.add_argument("--big-csv", type=Path, default=None)
    args = parser.parse_args()
    if args.big_csv is not None:
        big_csv(args.big_csv, args.repeats)
        return
    pts, bodies, defs = scene(args.minutes)
    cloud = cloud_from_points(pts, RATE)
    n = len(cloud)
    nb = min(args.baseline_frames, n)
    head = MarkerCloud(cloud.frame[:nb], cloud.t_s[:nb], cloud.xyz[:nb])
    track_cloud(head, defs)  # compile the kernels once, outside the timings
    tmp = Path(tempfile.mkdtemp())
    src = tmp / "points.csv"
    write_points_csv(src, pts)
    (tmp / "m.toml").write_text(tomli_w.dumps({"rigid_body": [
        {"name": b.name, "id": int(b.id), "markers": b.markers_body.tolist()} for b in bodies]}))
    rows = {"identities": [], "track (runs fitted at once)": [],
            "baseline: update() every frame": [], "end to end (read, track, write)": []}
    result = None
    for _ in range(args.repeats):
        _, w, c = timed(lambda: associate(cloud.xyz, cloud.counts(), cloud.frame))
        rows["identities"].append((n, w, c))
        result, w, c = timed(lambda: track_cloud(cloud, defs))
        rows["track (runs fitted at once)"].append((n, w, c))
        _, w, c = timed(lambda: track_cloud(head, defs, batched=False))
        rows["baseline: update() every frame"].append((nb, w, c))
        from calibkit.clitools import run_app
        from daemon.cli import app
        argv = sys.argv
        sys.argv = ["mocapd", "track", str(src), "--bodies", str(tmp / "m.toml"), "--rate",
                    "120", "--out", str(tmp / "poses.csv")]
        try:
            _, w, c = timed(lambda: _run(run_app, app))
        finally:
            sys.argv = argv
        rows["end to end (read, track, write)"].append((n, w, c))
    print(f"{n} frames ({args.minutes:g} min at {RATE:g} Hz), 10 bodies, "
          f"{int(np.median(cloud.counts()))} points a frame; {args.repeats} repeats, "
          "median / worst")
    print(f"{'what':>32s} | {'frames':>7s} | {'wall fps':>17s} | {'CPU fps':>17s} | "
          f"{'x baseline (CPU)':>16s}")
    base = np.median([f / c for f, _, c in rows["baseline: update() every frame"]])
    for name, runs in rows.items():
        wall = np.array([f / w for f, w, _ in runs])
        cpu = np.array([f / c for f, _, c in runs])
        print(f"{name:>32s} | {runs[0][0]:7d} | {np.median(wall):8.0f} / {wall.min():6.0f} | "
              f"{np.median(cpu):8.0f} / {cpu.min():6.0f} | {np.median(cpu) / base:16.1f}")
    dp, da, gross, valid = [], [], 0, 0
    for b, body in enumerate(bodies):
        v = result.valid[:, b]
        valid += v.sum()
        p = np.linalg.norm(result.position[v, b] - body.poses[v, :3, 3], axis=1) * 1000
        a = rotation_difference_deg(result.quaternion[v, b],
                                    quaternion_xyzw(body.poses[v, :3, :3]))
        gross += int(np.sum((p > 20) | (a > 5)))
        dp.append(p)
        da.append(a)
    dp, da = np.concatenate(dp), np.concatenate(da)
    print(f"poses: {valid} valid of {result.valid.size} ({100 * result.valid.mean():.1f}%); "
          f"position RMS {np.sqrt(np.mean(dp ** 2)):.3f} mm (max {dp.max():.2f}), "
          f"orientation RMS {np.sqrt(np.mean(da ** 2)):.3f} deg (max {da.max():.2f}); "
          f"gross {gross}")


READ_WHOLE = ("from daemon.formats.c3dio import read_points_csv as r; "
              "p = r({path!r}); print(len(p.frame))")
READ_STREAMED = ("from daemon.formats.points_csv import read_points_csv as r; "
                 "p, b = r({path!r}); print(len(p.frame))")


def _child(argv: list[str]) -> tuple[float, float, float]:
    """(wall s, CPU s, peak RSS MB) of one child process, its output dropped."""
    start = time.perf_counter()
    proc = subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - start
    err = proc.stderr.read().decode(errors="replace")
    proc.stderr.close()
    if os.waitstatus_to_exitcode(status) != 0:
        raise SystemExit(f"{' '.join(argv[:4])} ... failed: {err[-500:]}")
    return wall, usage.ru_utime + usage.ru_stime, usage.ru_maxrss / 1024.0


def big_csv(path: Path, repeats: int) -> None:
    """Time and peak memory of reading and tracking a big points CSV (see the docstring)."""
    bodies = path.parent / f"{path.name}.bodies.toml"
    out = Path(tempfile.mkdtemp()) / "poses.csv"
    py = sys.executable
    cases = {
        "read whole (c3dio, before)": [py, "-c", READ_WHOLE.format(path=str(path))],
        "read streamed (points_csv)": [py, "-c", READ_STREAMED.format(path=str(path))],
        "mocapd track (streamed read)": [py, "-m", "daemon.cli", "track", str(path),
                                         "--bodies", str(bodies), "--out", str(out)],
    }
    size_mb = path.stat().st_size / 1e6
    print(f"{path.name}: {size_mb:.0f} MB; {repeats} repeat(s), median (worst); "
          f"load {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
    print(f"{'what':>30s} | {'wall s':>15s} | {'CPU s':>15s} | {'peak RSS MB':>17s}")
    for name, argv in cases.items():
        runs = np.array([_child(argv) for _ in range(repeats)])
        med, worst = np.median(runs, axis=0), runs.max(axis=0)
        print(f"{name:>30s} | {med[0]:7.1f} ({worst[0]:5.1f}) | {med[1]:7.1f} "
              f"({worst[1]:5.1f}) | {med[2]:8.0f} ({worst[2]:6.0f})")
    out.unlink(missing_ok=True)


def _run(run_app, app):
    try:
        run_app(app, "mocapd")
    except SystemExit as exc:
        if exc.code:
            raise


if __name__ == "__main__":
    main()
