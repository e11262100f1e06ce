"""Where a correct labelled start and the marker set alone label one body differently.

Why: the issue asks that a correct start never end below the set alone; when a pattern of
bench_label_subjects.py does, this says on which points. The truth is read here only (the
labeller never sees it): each body of daemon/synthetic/subjects.py (seed), with 10 % of
marker-frames hidden and 2 ghosts a frame as the benchmark makes them, is labelled from
the set alone and from 10 labelled start frames; every point one run labels right and the
other does not is counted by (true marker, what the other run called it), and with
--frames listed frame by frame.

    python benchmarks/trace_label_start.py SEED [SEED ...] [--take 85_02] [--own] [--frames]
"""

from __future__ import annotations

import argparse
import sys
import warnings
from collections import Counter
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from daemon.formats.c3dio import read_c3d  # noqa: E402
from daemon.labelling.markerset import MarkerSet  # noqa: E402
from daemon.labelling.offline import label_take  # noqa: E402
from daemon.synthetic.labelling import hide_spans, points_with_ghosts  # noqa: E402
from daemon.synthetic.subjects import markers_of, random_subject, reproportion  # noqa: E402

START = 10


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("seeds", type=int, nargs="+")
    ap.add_argument("--take", default="85_02")
    ap.add_argument("--own", action="store_true", help="the take's own subject, not another")
    ap.add_argument("--frames", action="store_true", help="every differing point")
    args = ap.parse_args()
    warnings.simplefilter("ignore")
    ms = MarkerSet.load(ROOT / "daemon" / "labelling" / "sets" / "cmu41.toml")
    take0 = read_c3d(ROOT / "fixtures" / "cmu_c3d" / f"{args.take}.c3d").select(ms.labels)
    for seed in args.seeds:
        take = take0 if args.own else reproportion(take0, random_subject(seed, 0.15, 0.010, 0))
        t = hide_spans(take, 0.1, seed=seed)
        pts, mk = points_with_ghosts(t, 2, seed=seed)
        to_set = markers_of(t, ms.labels)
        truth = np.where(mk >= 0, to_set[np.maximum(mk, 0)], -1)
        order = np.argsort(pts.frame, kind="stable")
        _, first = np.unique(pts.frame[order], return_index=True)
        want = np.split(truth[order], first[1:])
        runs = {sf: label_take(pts, ms, take.rate_hz, t if sf else None, sf)[2]
                for sf in (0, START)}

        def name(m):
            return "unlabelled" if m < 0 else ms.labels[m]

        lost, gained = Counter(), Counter()
        for i in range(START, len(want)):
            alone, start, w = runs[0][i], runs[START][i], want[i]
            for j in np.flatnonzero((alone == w) & (start != w) & (w >= 0)):
                lost[(ms.labels[w[j]], name(start[j]))] += 1
                if args.frames:
                    print(f"{seed}: frame {i} {ms.labels[w[j]]}: the start's run "
                          f"{name(start[j])}")
            for j in np.flatnonzero((alone != w) & (start == w) & (w >= 0)):
                gained[(ms.labels[w[j]], name(alone[j]))] += 1
        print(f"{args.take} seed {seed}{' (own subject)' if args.own else ''}: right from "
              f"the set alone, not with the start: "
              f"{dict(lost.most_common()) or 'none'}; the other way: "
              f"{dict(gained.most_common()) or 'none'}")


if __name__ == "__main__":
    main()
