"""Issue 29's target on a synthetic stand-in: a Motive 1.0 take, four bodies, one 4 mm off.

Scene (daemon.synthetic.motive_export.write_motive_1_0): a format 1.0 export, y-up, of four
bodies (4, 3, 6 and 5 markers) moving through a 4 m room for --frames at 120 Hz, 0.2 mm
noise per axis, 2 % of marker-frames hidden, two strays a frame; Motive's poses are the
simulator's truth wherever a body has three markers in view; body 0's exported definition
has one marker --off-mm off (moved away from its nearest neighbour). One take per repeat
(seeds 21, 22, ...). Each take goes through what `mocapd track take.csv --bodies-from-file`
runs (read, turn to z-up, fit the definitions, track), with the refinement at its default
(auto) and, as the baseline in the same process, off. Per row, medians over the repeats:
the share of Motive's tracked frames each body is posed in within 1 mm and 1 deg of
Motive's pose (the worst body's, and the off body's), the position and orientation error
over all valid poses, and the time of the whole run (wall clock, and this process's CPU
time: the machine may be shared).

With --speed-minutes M it also times the refinement alone (refine_bodies, auto) on
bench_track.py's scene (10 bodies of 4-5 markers, 45 points a frame, M minutes at 120 Hz)
beside the tracking of that take (track_cloud, the baseline), CPU time, median of repeats.

    python benchmarks/bench_motive_refine.py [--repeats 3] [--frames 752] [--off-mm 4]
                                             [--speed-minutes 2]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from daemon.analysis.offline_track import rotation_difference_deg
from daemon.analysis.track_file import bodies_from_motive, load_markers, track_file
from daemon.synthetic.motive_export import write_motive_1_0
from daemon.tracking.rigid import RigidConfig


def run(path: Path, refine: str) -> dict:
    """One `mocapd track --bodies-from-file` run in this process, scored against Motive."""
    start, cpu = time.perf_counter(), time.process_time()
    cloud, motive, _, _ = load_markers(path, None)
    defs = bodies_from_motive(motive, path)
    table, _, _ = track_file(cloud, motive, defs, RigidConfig(), 30.0, 20.0, refine=refine)
    elapsed, cpu = time.perf_counter() - start, time.process_time() - cpu
    good, dp_all, da_all = [], [], []
    for b, body in enumerate(defs):
        theirs = motive.poses[body.name]
        both = theirs.valid & table.valid[:, b]
        dp = np.linalg.norm(table.xyz[:, b] - theirs.xyz_m, axis=1) * 1000.0
        da = rotation_difference_deg(table.quat[:, b], theirs.quat_xyzw)
        ok = both & (dp < 1.0) & (da < 1.0)
        good.append(ok.sum() / max(theirs.valid.sum(), 1))
        dp_all.append(dp[both])
        da_all.append(da[both])
    return {"worst": min(good), "off_body": good[0], "pos_mm": np.median(np.concatenate(dp_all)),
            "ang_deg": np.median(np.concatenate(da_all)), "time_s": elapsed, "cpu_s": cpu,
            "frames": len(cloud)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--frames", type=int, default=752)
    parser.add_argument("--off-mm", type=float, default=4.0)
    parser.add_argument("--speed-minutes", type=float, default=0.0)
    args = parser.parse_args()
    rows = {"auto": [], "off": []}
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(args.repeats):
            path = Path(tmp) / f"take{r}.csv"
            write_motive_1_0(path, n_frames=args.frames, seed=21 + r, off_mm=args.off_mm)
            for mode in rows:
                rows[mode].append(run(path, mode))
    print(f"{args.repeats} takes of {args.frames} frames, definition {args.off_mm:g} mm off; "
          "medians over the takes")
    print("| refine | worst body, frames within 1 mm / 1 deg | off body | position err mm "
          "(median) | orientation err deg (median) | run s (wall) | run s (CPU) |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    for mode, label in (("auto", "auto (default)"), ("off", "off (baseline)")):
        med = {k: float(np.median([x[k] for x in rows[mode]])) for k in rows[mode][0]}
        worst = min(x["worst"] for x in rows[mode])
        print(f"| {label} | {100 * med['worst']:.2f} % (lowest {100 * worst:.2f} %) | "
              f"{100 * med['off_body']:.2f} % | {med['pos_mm']:.3f} | {med['ang_deg']:.3f} | "
              f"{med['time_s']:.2f} | {med['cpu_s']:.2f} |")
    if args.speed_minutes > 0:
        speed(args.speed_minutes, args.repeats)


def speed(minutes: float, repeats: int) -> None:
    """The refinement's cost beside the tracking's, on bench_track.py's scene."""
    from bench_track import scene

    from daemon.analysis.body_refine import refine_bodies
    from daemon.analysis.offline_track import cloud_from_points, track_cloud

    pts, _, defs = scene(minutes)
    cloud = cloud_from_points(pts, 120.0)
    cost = {"refine_bodies (auto), 10 bodies": [], "track_cloud (baseline)": []}
    for _ in range(repeats):
        c = time.process_time()
        refine_bodies(cloud.xyz, defs, RigidConfig().distance_tol_m, "auto")
        cost["refine_bodies (auto), 10 bodies"].append(time.process_time() - c)
        c = time.process_time()
        track_cloud(cloud, defs, RigidConfig(refine=False))
        cost["track_cloud (baseline)"].append(time.process_time() - c)
    print(f"\n{len(cloud)} frames ({minutes:g} min at 120 Hz), 10 bodies, 45 points a frame; "
          f"CPU s, median / worst of {repeats}")
    print("| what | CPU s |")
    print("| --- | --- |")
    for what, v in cost.items():
        print(f"| {what} | {np.median(v):.2f} / {max(v):.2f} |")


if __name__ == "__main__":
    main()
