"""Labelling accuracy and speed on the real CMU takes, labels stripped, points shuffled.

For each take: gap-free, and with 20 % of marker-frames hidden in spans of 0.1-1 s plus
3 ghost points per frame (uniform in the body's bounding box grown by 0.1 m). Started
from 10 labelled frames (--start-frames 10) or from the marker set alone. Marker sets:
the shipped cmu41 (learned from both takes, so the same subjects) and one learned from
the *other* take only (another person: a harder, cross-subject case). The baseline is
every frame labelled from scratch by matching segments by their distances (our
`initial_labels`, the per-frame method tracking replaced), on every 20th frame because
it is slow.

    python benchmarks/bench_label.py [--repeats 5] [--speed-only] [--sweep 30]
        [--hidden 0.1 --ghosts 2] [--start-frames 10]

--sweep N: only one occlusion case (cmu41, --hidden/--ghosts, default 20 %/3, with
--start-frames, default 10; 0: from the marker set alone) over N occlusion/ghost patterns
per take (RNG seeds 0..N-1): median, worst and how many fall below 97 %, since five patterns
say little about the worst. fps_cpu in the tables is the whole labelling (label_take,
the start from the set alone included), per CPU second.

Speed: Labeller.update alone, compiled kernels (daemon/labelling/kernels.py) against their
numpy twins (Labeller(compiled=False)) in the same process.
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
from daemon.formats.c3dio import read_c3d  # noqa: E402
from daemon.labelling.labeller import Labeller  # noqa: E402
from daemon.labelling.markerset import MarkerSet, learn  # noqa: E402
from daemon.labelling.offline import label_take  # noqa: E402
from daemon.labelling.single import initial_labels  # noqa: E402
from daemon.synthetic.labelling import hide_spans, points_with_ghosts, score  # noqa: E402

DATA = ROOT / "fixtures" / "cmu_c3d"


def run(take, ms, hidden, ghosts, start_frames, seed):
    t = hide_spans(take, hidden, seed=seed) if hidden else take
    pts, truth = points_with_ghosts(t, ghosts, seed=seed)
    c0 = time.process_time()
    _, _, labels = label_take(pts, ms, take.rate_hz, t if start_frames else None, start_frames)
    cpu = time.process_time() - c0
    s = score(pts, truth, labels, start_frames)
    return s["correct"], s["ghosts_rejected"], (take.n_frames - start_frames) / cpu


def baseline(take, ms, hidden, ghosts, seed, every=20):
    """Every frame from scratch (per-frame module matching, no tracking)."""
    t = hide_spans(take, hidden, seed=seed) if hidden else take
    pts, truth = points_with_ghosts(t, ghosts, seed=seed)
    frames, per = pts.split()
    order = np.argsort(pts.frame, kind="stable")
    tm = np.split(truth[order], np.unique(pts.frame[order], return_index=True)[1][1:])
    good = total = 0
    c0 = time.process_time()
    n = 0
    for i in range(0, len(frames), every):
        lab = initial_labels(per[i], ms)
        real = tm[i] >= 0
        good += int((lab[real] == tm[i][real]).sum())
        total += int(real.sum())
        n += 1
    cpu = time.process_time() - c0
    return good / max(total, 1), n / cpu


def speed(take, ms, hidden=0.0, ghosts=0, seed=0, compiled=True):
    """Frames per second of CPU time of Labeller.update alone (after 10 labelled start frames);
    compiled=False runs the numpy twins of the compiled kernels (the baseline)."""
    t = hide_spans(take, hidden, seed=seed) if hidden else take
    pts, _ = points_with_ghosts(t, ghosts, seed=seed)
    _, per = pts.split()
    lab = Labeller(ms, take.rate_hz, compiled=compiled)
    lab.start_from_labelled_frames(t.xyz_m[:10])
    c0 = time.process_time()
    for p in per[10:]:
        lab.update(p)
    return (len(per) - 10) / (time.process_time() - c0)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--speed-only", action="store_true")
    ap.add_argument("--sweep", type=int, default=0, metavar="N")
    ap.add_argument("--hidden", type=float, default=0.2)
    ap.add_argument("--ghosts", type=int, default=3)
    ap.add_argument("--start-frames", type=int, default=10)
    args = ap.parse_args()
    warnings.simplefilter("ignore")
    shipped = MarkerSet.load(ROOT / "daemon" / "labelling" / "sets" / "cmu41.toml")
    takes = {n: read_c3d(DATA / f"{n}.c3d").select(shipped.labels) for n in ("85_02", "01_01")}
    if args.speed_only:
        return speed_table(takes, shipped, args.repeats)
    if args.sweep:
        return sweep_table(takes, shipped, args.sweep, args.hidden, args.ghosts,
                           args.start_frames)
    other = {"85_02": learn([takes["01_01"]]), "01_01": learn([takes["85_02"]])}
    rows = []
    for name, take in takes.items():
        for set_name, ms in (("cmu41", shipped), ("other", other[name])):
            for hidden, ghosts in ((0.0, 0), (0.2, 3)):
                for start_frames in (10, 0):
                    res = [run(take, ms, hidden, ghosts, start_frames, s)
                           for s in range(args.repeats)]
                    c, g, fps = (np.median([r[i] for r in res]) for i in range(3))
                    worst = min(r[0] for r in res)
                    rows.append([name, set_name, f"{int(hidden * 100)}%/{ghosts}",
                                 start_frames, round(100 * c, 2), round(100 * worst, 2),
                                 round(100 * g, 1), round(fps)])
                    print(*rows[-1], flush=True, file=sys.stderr)
    print_table(rows, ["take", "markerset", "hidden/ghosts", "start_frames", "correct_%",
                       "worst_%", "ghosts_rejected_%", "fps_cpu"])
    print()
    rows = []
    for name, take in takes.items():
        for hidden, ghosts in ((0.0, 0), (0.2, 3)):
            acc, fps_b = baseline(take, shipped, hidden, ghosts, 0)
            ours = run(take, shipped, hidden, ghosts, 0, 0)
            rows.append([name, f"{int(hidden * 100)}%/{ghosts}", round(100 * acc, 2),
                         round(fps_b, 1), round(100 * ours[0], 2), round(ours[2]),
                         round(ours[2] / fps_b, 1)])
    print("baseline: every frame from scratch vs tracking, cmu41, no labelled frame")
    print_table(rows, ["take", "hidden/ghosts", "baseline_%", "baseline_fps", "ours_%",
                       "ours_fps", "speedup"])
    print()
    speed_table(takes, shipped, args.repeats)


def sweep_table(takes, ms, n, hidden=0.2, ghosts=3, start_frames=10):
    """One occlusion case over n patterns per take."""
    rows = []
    for name, take in takes.items():
        got, fps = [], []
        for s in range(n):
            c, _, f = run(take, ms, hidden, ghosts, start_frames, s)
            got.append(100 * c)
            fps.append(f)
            print(name, s, round(got[-1], 2), round(f), flush=True, file=sys.stderr)
        got = np.array(got)
        low = ", ".join(f"{s}: {v:.1f}" for s, v in enumerate(got) if v < 97)
        rows.append([name, n, round(float(np.median(got)), 2), round(float(got.min()), 2),
                     int((got < 97).sum()), low or "-", round(float(np.median(fps))),
                     round(float(np.min(fps)))])
    print(f"cmu41, {round(100 * hidden)} % hidden + {ghosts} ghosts, {start_frames} labelled "
          f"start frames, one row per take")
    print_table(rows, ["take", "patterns", "correct_%_median", "worst_%", "below_97",
                       "patterns_below_97", "fps_cpu_median", "fps_cpu_worst"])


def speed_table(takes, ms, repeats):
    """Median frames/s over `repeats` runs (occlusion patterns 0..repeats-1), compiled
    kernels against their numpy twins run alternately in the same process."""
    first = next(iter(takes.values()))
    speed(first, ms, 0.2, 3, 0)                        # compile / load the kernels first
    rows = []
    for name, take in takes.items():
        for hidden, ghosts in ((0.0, 0), (0.2, 3)):
            fast, slow = [], []
            for s in range(repeats):
                fast.append(speed(take, ms, hidden, ghosts, s))
                slow.append(speed(take, ms, hidden, ghosts, s, compiled=False))
            rows.append([name, f"{int(hidden * 100)}%/{ghosts}", round(np.median(fast)),
                         round(min(fast)), round(np.median(slow)),
                         round(np.median(fast) / np.median(slow), 2)])
    print("Labeller.update, 41 markers (CPU time, one core), frames/s")
    print_table(rows, ["take", "hidden/ghosts", "fps_median", "fps_worst", "numpy_fps",
                       "speedup"])


if __name__ == "__main__":
    main()
