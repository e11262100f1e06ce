"""Speed of labelling a whole take (`label_take`), from the marker set alone and from 10
labelled start frames, on both CMU takes (labels stripped, points shuffled).

    python benchmarks/bench_label_take.py [--repeats 3]

Prints frames/s of CPU time (median of the repeats, after a warm-up run that loads the
compiled kernels). To compare with another version of the labeller, run the same script
with PYTHONPATH at that version's tree (e.g. `git archive REV daemon calibkit projector
fixtures/cmu_c3d | tar -x -C /tmp/old`); it finds `label_take` where that version has it.
"""

from __future__ import annotations

import argparse
import sys
import time
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from daemon.markers.c3dio import Points, read_c3d  # noqa: E402
from daemon.markers.markerset import open_set  # noqa: E402

try:
    from daemon.markers.label_offline import label_take  # noqa: E402
except ImportError:                      # a version before the labeller was split
    from daemon.markers.label import label_take  # noqa: E402

DATA = ROOT / "fixtures" / "cmu_c3d"


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    warnings.simplefilter("ignore")
    cmu = open_set("cmu41")
    warm = read_c3d(DATA / "85_02.c3d").select(cmu.labels)
    label_take(Points.from_take(warm, seed=9), cmu, 120.0)
    rows = []
    for name in ("85_02", "01_01"):
        take = read_c3d(DATA / f"{name}.c3d").select(cmu.labels)
        pts = Points.from_take(take, seed=1)
        for start_frames in (0, 10):
            fps = []
            for _ in range(args.repeats):
                c0 = time.process_time()
                label_take(pts, cmu, take.rate_hz, take if start_frames else None,
                           start_frames)
                fps.append(take.n_frames / (time.process_time() - c0))
            rows.append([name, take.n_frames, start_frames, round(float(np.median(fps))),
                         round(float(np.min(fps)))])
            print(*rows[-1], flush=True, file=sys.stderr)
    from calibkit.clitools import print_table
    print("label_take, cmu41, clean takes, frames/s of CPU time")
    print_table(rows, ["take", "frames", "start_frames", "fps_median", "fps_worst"])


if __name__ == "__main__":
    main()
