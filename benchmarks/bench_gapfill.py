"""Gap filling error against removed truth on the real CMU takes, per span length.

Spans of 0.1, 0.25, 0.5 and 1 s are cut from random markers (8 per trial, in different
markers, at random times), filled by each method in the same run, and the RMS error over
the removed samples is reported in millimetres: linear, cubic spline, the third seed's
Newton fill (module centre + carried shape), rigid (weighted fit of steady markers), PCA
(low-rank fill over the take) and `auto` (per gap, chosen by trial fills). No marker set
is given: the fill learns the markers' steadiness from the take itself.

    python benchmarks/bench_gapfill.py [--trials 5]
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

from calibkit.clitools import print_table  # noqa: E402
from daemon.analysis.gapfill import fill  # noqa: E402
from daemon.formats.c3dio import Take, read_c3d  # noqa: E402

DATA = ROOT / "fixtures" / "cmu_c3d"
METHODS = ("linear", "cubic", "newton", "pca", "rigid", "auto")
SPANS_S = (0.1, 0.25, 0.5, 1.0)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--trials", type=int, default=5)
    args = ap.parse_args()
    warnings.simplefilter("ignore")
    rows = []
    for name in ("85_02", "01_01"):
        take = read_c3d(DATA / f"{name}.c3d")
        take = take.select([n for n in take.labels if n not in ("RBAC-1", "RBAC")]) \
            if name == "01_01" else take
        if name == "01_01":
            take = Take(take.labels, take.xyz_m[:1500], take.rate_hz)
        rng = np.random.default_rng(0)
        for span in SPANS_S:
            L = int(round(span * take.rate_hz))
            sq = {m: [] for m in METHODS}
            cpu = {m: 0.0 for m in METHODS}
            for _ in range(args.trials):
                x = take.xyz_m.copy()
                cuts = []
                for m in rng.choice(len(take.labels), 8, replace=False):
                    s = int(rng.integers(5, take.n_frames - L - 5))
                    cuts.append((int(m), s))
                    x[s:s + L, m] = np.nan
                cut = Take(take.labels, x, take.rate_hz)
                for method in METHODS:
                    c0 = time.process_time()
                    out, _ = fill(cut, method=method)
                    cpu[method] += time.process_time() - c0
                    for m, s in cuts:
                        sq[method].append(np.sum((out.xyz_m[s:s + L, m]
                                                  - take.xyz_m[s:s + L, m]) ** 2, axis=1))
            rms = {m: 1000 * float(np.sqrt(np.mean(np.concatenate(v)))) for m, v in sq.items()}
            rows.append([name, span, *[round(rms[m], 1) for m in METHODS],
                         round(rms["cubic"] / rms["auto"], 1),
                         round(1000 * cpu["auto"] / args.trials, 1)])
            print(*rows[-1], file=sys.stderr, flush=True)
    print("RMS error (mm) over removed samples; 8 gaps per trial")
    print_table(rows, ["take", "span_s", *[f"{m}_mm" for m in METHODS], "cubic/auto",
                       "auto_ms_per_trial"])


if __name__ == "__main__":
    main()
