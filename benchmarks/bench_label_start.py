"""Labelling from the marker set alone on bodies the set was not learned on.

Cases: the two CMU takes with the bundled cmu41 set (learned from both) and with a set
learned on the *other* take only (another person); the simulator's walker in its
standard body and three others (tests/label_people.py: short and broad, tall and thin,
long legs; markers 12-15 mm off their places), with cmu41 and with the set of the
simulator's standard person. Labels stripped, points shuffled, no labelled frame; the
whole `label_take` (start included) timed in CPU seconds.

    python benchmarks/bench_label_start.py [--hidden 0.1 --ghosts 2] [--patterns 3]

--patterns N: occlusion/ghost patterns (seeds 0..N-1) per case; the table gives the
median and worst share named right, the worst share named wrong, frames/s (median).
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
sys.path.insert(0, str(ROOT / "tests"))

from label_people import BODIES, Body, walk  # noqa: E402

from calibkit.clitools import print_table  # noqa: E402
from daemon.formats.c3dio import Take, read_c3d  # noqa: E402
from daemon.labelling.markerset import learn, open_set  # noqa: E402
from daemon.labelling.offline import label_take  # noqa: E402
from daemon.synthetic.labelling import hide_spans, points_with_ghosts, score  # noqa: E402

DATA = ROOT / "fixtures" / "cmu_c3d"


def person(body: Body, labels: list[str], frames: int = 600) -> Take:
    w = walk(body, frames)
    idx = [w.labels.index(n) for n in labels]
    return Take(list(labels), w.markers_m[:, idx], w.rate_hz, 0)


def cases():
    cmu = open_set("cmu41")
    sim = open_set("sim_person")
    takes = {n: read_c3d(DATA / f"{n}.c3d").select(cmu.labels) for n in ("01_01", "85_02")}
    yield "01_01", "cmu41", takes["01_01"], cmu
    yield "85_02", "cmu41", takes["85_02"], cmu
    yield "85_02", "learned on 01_01", takes["85_02"], learn([takes["01_01"]])
    yield "01_01", "learned on 85_02", takes["01_01"], learn([takes["85_02"]])
    for name, body in [("walker standard", Body()),
                       *((f"walker {k}", b) for k, b in BODIES.items())]:
        t = person(body, cmu.labels)
        yield name, "cmu41", t, cmu
        yield name, "sim_person", t.select(sim.labels), sim


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--hidden", type=float, default=0.0)
    ap.add_argument("--ghosts", type=int, default=0)
    ap.add_argument("--patterns", type=int, default=1)
    args = ap.parse_args()
    warnings.simplefilter("ignore")
    rows = []
    for name, set_name, take, ms in cases():
        right, wrong, fps = [], [], []
        for seed in range(args.patterns):
            t = hide_spans(take, args.hidden, seed=seed) if args.hidden else take
            pts, truth = points_with_ghosts(t, args.ghosts, seed=seed)
            c0 = time.process_time()
            _, _, labels = label_take(pts, ms, take.rate_hz)
            fps.append(take.n_frames / (time.process_time() - c0))
            s = score(pts, truth, labels)
            right.append(100 * s["correct"])
            wrong.append(100 * max(0.0, 1 - s["correct"] - s["unlabelled"]))
            print(name, set_name, seed, round(right[-1], 2), round(fps[-1]), flush=True,
                  file=sys.stderr)
        rows.append([name, set_name, take.n_frames, round(float(np.median(right)), 2),
                     round(min(right), 2), round(max(wrong), 2), round(float(np.median(fps)))])
    print(f"from the marker set alone, {round(100 * args.hidden)} % hidden + {args.ghosts} "
          f"ghosts, {args.patterns} pattern(s) per case")
    print_table(rows, ["take", "marker set", "frames", "right_%_median", "right_%_worst",
                       "wrong_%_worst", "fps_cpu"])


if __name__ == "__main__":
    main()
