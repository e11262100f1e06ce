"""Tracing one body of bench_label_subjects: where its labels from the set alone go wrong.

The truth is read here only (never by the labeller): the start window's labels against
it, whether the take was labelled again and from which window, and per 60 frames the
right / wrong % with the markers whose points went elsewhere (truth -> label found).

    python benchmarks/trace_label_subjects.py SEED [--take 85_02] [--no-verify]
"""

from __future__ import annotations

import argparse
import sys
import time
import warnings
from collections import Counter
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from daemon.formats.c3dio import read_c3d  # noqa: E402
from daemon.labelling import offline  # noqa: E402
from daemon.labelling.markerset import MarkerSet  # noqa: E402
from daemon.synthetic.labelling import hide_spans, points_with_ghosts  # noqa: E402
from daemon.synthetic.subjects import markers_of, random_subject, reproportion  # noqa: E402


def errors(got, want, names, top=6):
    """Right %, wrong % and the commonest (truth, label) mistakes of a set of points."""
    real = want >= 0
    g, w = got[real], want[real]
    bad = Counter((names[a], names[b] if b >= 0 else "-")
                  for a, b in zip(w, g, strict=True) if a != b)
    return 100 * (g == w).mean(), 100 * ((g >= 0) & (g != w)).mean(), bad.most_common(top)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("seed", type=int)
    ap.add_argument("--take", default="85_02")
    ap.add_argument("--no-verify", action="store_true")
    args = ap.parse_args()
    warnings.simplefilter("ignore")
    ms = MarkerSet.load(ROOT / "daemon" / "labelling" / "sets" / "cmu41.toml")
    take = read_c3d(ROOT / "fixtures" / "cmu_c3d" / f"{args.take}.c3d").select(ms.labels)
    t = hide_spans(reproportion(take, random_subject(args.seed)), 0.1, seed=args.seed)
    pts, mk = points_with_ghosts(t, 2, seed=args.seed)
    to_set = markers_of(t, ms.labels)
    truth = np.where(mk >= 0, to_set[np.maximum(mk, 0)], -1)
    order = np.argsort(pts.frame, kind="stable")
    _, st = np.unique(pts.frame[order], return_index=True)
    want = np.split(truth[order], st[1:])
    seen: dict = {"starts": [], "again": []}
    window_start, better = offline.window_start, offline._better_window

    def spy_start(*a, **k):
        seen["starts"].append(window_start(*a, **k))
        return seen["starts"][-1]

    def spy_better(*a, **k):
        seen["again"].append(better(*a, **k))
        return seen["again"][-1]

    offline.window_start, offline._better_window = spy_start, spy_better
    t0 = time.time()
    _, _, labels = offline.label_take(pts, ms, take.rate_hz, None, 0,
                                      verify=not args.no_verify)
    print(f"body {args.seed} on {args.take}: {time.time() - t0:.0f} s wall")
    n = len(want)
    r, w, _ = errors(np.concatenate(labels), np.concatenate(want), ms.labels)
    print(f"whole take: right {r:.2f} %, wrong {w:.2f} %")
    for w0, wl, _ in seen["starts"]:
        r, w, bad = errors(np.concatenate(wl), np.concatenate(want[w0:w0 + len(wl)]),
                           ms.labels, 12)
        print(f"start window at frame {w0}: right {r:.2f} %, wrong {w:.2f} %; {bad}")
    for a in seen["again"]:
        print("labelled again from frame", None if a is None else a[0])
    for a in range(0, n, 60):
        rng = range(a, min(a + 60, n))
        r, w, bad = errors(np.concatenate([labels[i] for i in rng]),
                           np.concatenate([want[i] for i in rng]), ms.labels)
        print(f"frames {a}-{rng[-1]}: {r:.1f} / {w:.1f}  {bad}")


if __name__ == "__main__":
    main()
