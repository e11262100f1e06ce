"""What live labelling adds to the daemon's frame loop: the simulated walking person (41
markers) and a rigid body, tracked with and without `markerset = "sim_person"`.

Each run is `mocapd start --sim` as fast as the loop goes (realtime = false: every frame
tracked and labelled in order). The figures are per frame, from arrival to the poses and
labels being ready for the outputs (the pipeline's latency_to_poses), after the start from
the marker set has been accepted (the first `--skip` frames are left out; the start itself
runs on a thread of its own when the daemon is paced by cameras). The stage's own time is
the labelling stage's clock. Medians over repeated runs; the ratio is against the runs
without a marker set in the same process.

Then `--paced` runs paced at the scene's 120 fps (as with cameras: the start searched on
a thread, frames skipped when the loop falls behind), scored against the person's truth.

    nice -n 10 python benchmarks/bench_live_label.py [--frames 1500] [--runs 3] [--paced 3]
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
from pathlib import Path

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from daemon.config.mocapd import parse_config  # noqa: E402
from daemon.service.daemon import Daemon  # noqa: E402

SIM = {"cameras": 6, "bodies": 1, "markers_per_body": 4, "fps": 120.0, "noise_px": 0.2,
       "seed": 7, "person": True, "realtime": False}


def paced(frames: int, runtime: Path) -> dict:
    data = {"sim": {**SIM, "realtime": True}, "runtime_dir": str(runtime),
            "markerset": "sim_person"}
    d = Daemon(parse_config(data, None, Path.cwd()))
    fig = d.run(frames=frames)
    score = fig["truth"]["labelling"]
    return {"named_right": score["named_right_fraction"],
            "labelled_frames": score["frames"] / frames,
            "skipped": fig["multiplexer"]["skipped_behind"],
            "median_ms": fig["latency_to_poses"]["median_ms"],
            "p99_ms": fig["latency_to_poses"]["p99_ms"]}


def run(frames: int, skip: int, markerset: bool, runtime: Path) -> dict:
    data = {"sim": SIM, "runtime_dir": str(runtime)}
    if markerset:
        data["markerset"] = "sim_person"
    d = Daemon(parse_config(data, None, Path.cwd()))
    d.run(frames=frames)
    lat = np.array(d.pipeline.stats.all_latency[skip:], np.float64) * 1e-6
    out = {"median_ms": float(np.median(lat)), "p99_ms": float(np.percentile(lat, 99))}
    if markerset:
        stage = np.array(list(d.labelling.time_ns)[skip - frames:], np.float64) * 1e-6
        out.update(stage_median_ms=float(np.median(stage)),
                   stage_p99_ms=float(np.percentile(stage, 99)))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=1500)
    ap.add_argument("--skip", type=int, default=300)
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--paced", type=int, default=0, help="paced runs (0: none)")
    args = ap.parse_args()
    rows = {False: [], True: []}
    with tempfile.TemporaryDirectory() as tmp:
        for i in range(args.runs):
            for with_set in (False, True):
                rows[with_set].append(run(args.frames, args.skip, with_set, Path(tmp) / str(i)))
    base = {k: float(np.median([r[k] for r in rows[False]])) for k in ("median_ms", "p99_ms")}
    lab = {k: float(np.median([r[k] for r in rows[True]])) for k in rows[True][0]}
    print(f"{args.runs} runs x {args.frames} frames ({args.skip} skipped), 6 cameras, "
          "41-marker person + 1 rigid body, 120 fps scene, as fast as possible")
    print(f"{'':28s} {'median ms':>10s} {'p99 ms':>10s}")
    print(f"{'frame, no marker set':28s} {base['median_ms']:10.3f} {base['p99_ms']:10.3f}")
    print(f"{'frame, markerset sim_person':28s} {lab['median_ms']:10.3f} {lab['p99_ms']:10.3f}")
    print(f"{'  ratio':28s} {lab['median_ms'] / base['median_ms']:10.2f} "
          f"{lab['p99_ms'] / base['p99_ms']:10.2f}")
    print(f"{'  added':28s} {lab['median_ms'] - base['median_ms']:10.3f} "
          f"{lab['p99_ms'] - base['p99_ms']:10.3f}")
    print(f"{'labelling stage alone':28s} {lab['stage_median_ms']:10.3f} "
          f"{lab['stage_p99_ms']:10.3f}")
    if not args.paced:
        return
    print(f"\npaced at 120 fps, {args.frames} frames a run")
    print(f"{'run':>4s} {'named right':>12s} {'frames labelled':>16s} {'skipped':>8s} "
          f"{'median ms':>10s} {'p99 ms':>8s}")
    with tempfile.TemporaryDirectory() as tmp:
        for i in range(args.paced):
            r = paced(args.frames, Path(tmp) / f"p{i}")
            print(f"{i + 1:4d} {r['named_right']:12.4f} {r['labelled_frames']:16.3f} "
                  f"{r['skipped']:8d} {r['median_ms']:10.3f} {r['p99_ms']:8.3f}")


if __name__ == "__main__":
    main()
