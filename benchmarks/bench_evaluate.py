"""How well `mocapd evaluate` recovers a robot log's clock and frame
(daemon.analysis.trajectory_eval).

Scene (daemon.synthetic.trajectory.flight): a drone flies 60 s through a 4 m room; motion
capture logs it at 120 Hz, the robot at 50 Hz (uneven) on its own clock (offset 0.237 s,
drift 50 ppm) and in its own world frame; both logs carry 1 mm and 0.1 deg of noise. Rows:
the full fit (offset, drift and alignment together, robust) against the baseline of the
coarse speed cross-correlation with a rigid Umeyama fit at that offset, in the same
process. Alignment error: RMS displacement over the flight between the fitted and the true
alignment. Median and worst over the seeds.

    python benchmarks/bench_evaluate.py [--seeds 10] [--noise-mm 1]
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from scipy.spatial.transform import Rotation

from daemon.analysis.trajectory_eval import coarse_offset, evaluate
from daemon.synthetic.trajectory import flight


def _errors(ev, truth, robot) -> list[float]:
    ours = ev.alignment.apply(robot.xyz)
    true = truth.scale * robot.xyz @ truth.R.T + truth.t
    disp = float(np.sqrt(np.mean(np.sum((ours - true) ** 2, axis=1))))
    angle = float(np.degrees(Rotation.from_matrix(ev.alignment.R.T @ truth.R).magnitude()))
    return [abs(ev.time.offset_s - truth.offset_s) * 1e3,
            abs(ev.time.drift - truth.drift) * 1e6, disp * 1e3, angle]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=10)
    parser.add_argument("--noise-mm", type=float, default=1.0)
    args = parser.parse_args()
    rows = {"full fit": [], "baseline: xcorr + Umeyama": []}
    times = {k: [] for k in rows}
    for seed in range(args.seeds):
        mocap, robot, truth = flight(60.0, noise_m=args.noise_mm / 1000, seed=seed)
        for name in rows:
            start = time.perf_counter()
            if name == "full fit":
                ev = evaluate(mocap, robot)
            else:
                ev = evaluate(mocap, robot, known_offset_s=coarse_offset(mocap, robot, 2.0),
                              fit_drift=False)
            times[name].append(time.perf_counter() - start)
            rows[name].append(_errors(ev, truth, robot))
    print(f"{args.seeds} flights of 60 s, {args.noise_mm:g} mm noise; median / worst")
    header = ["method", "offset err (ms)", "drift err (ppm)", "alignment (mm)",
              "rotation (deg)", "time (s)"]
    print(" | ".join(f"{h:>26s}" if i == 0 else f"{h:>16s}" for i, h in enumerate(header)))
    base_t = float(np.median(times["baseline: xcorr + Umeyama"]))
    for name, values in rows.items():
        v = np.array(values)
        cells = [f"{np.median(v[:, k]):.4f} / {v[:, k].max():.4f}" for k in range(4)]
        t = float(np.median(times[name]))
        cells.append(f"{t:.2f} ({t / base_t:.1f}x)")
        print(f"{name:>26s} | " + " | ".join(f"{c:>16s}" for c in cells))


if __name__ == "__main__":
    main()
