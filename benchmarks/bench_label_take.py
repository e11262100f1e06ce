"""Speed of labelling a whole take (`label_take`), from the marker set alone and from 10
labelled start frames, on both CMU takes (labels stripped, points shuffled).

    python benchmarks/bench_label_take.py [--repeats 3] [--command] [--subjects 0,1,2]

Prints frames/s of CPU time (median of the repeats, after a warm-up run). --command: the
whole `mocapd label POINTS.csv --markerset cmu41 --out X.c3d` instead, Python's start and
imports included (user + system CPU time of the child process, best of the repeats: the
least disturbed by the machine's other work), on the takes' points written as CSV, after
one untimed run that caches the bytecode of every module the command loads.
--subjects SEEDS (with --command): each take also performed by those other bodies
(daemon/synthetic/subjects.py: segments re-proportioned +-15 %, markers 10 mm off).
With --command each take's row also gives the fixed part: the same command on the take's
first 10 frames (start-up, imports, the marker set, the start window's assignment), and
the per-frame rate of the rest ((frames - 10) / (CPU - fixed)); and the table ends with
the start-up alone (`python -c "import numpy"`, `mocapd label --help`), same conditions.

To compare with another version of the labeller, run the same script
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

from daemon.formats.c3dio import Points, read_c3d  # noqa: E402
from daemon.labelling.markerset import open_set  # noqa: E402

try:
    from daemon.labelling.offline import label_take  # noqa: E402
except ImportError:                      # a version before the labeller was split
    from daemon.labelling.labeller import label_take  # noqa: E402

DATA = ROOT / "fixtures" / "cmu_c3d"


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--command", action="store_true")
    ap.add_argument("--subjects", default="", help="seeds of other bodies (--command)")
    args = ap.parse_args()
    warnings.simplefilter("ignore")
    cmu = open_set("cmu41")
    if args.command:
        seeds = [int(v) for v in args.subjects.split(",") if v]
        return command_table(cmu, args.repeats, seeds)
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


def command_table(cmu, repeats: int, subjects: list[int] | None = None) -> None:
    """The whole command, start-up included, from the set alone, in child processes."""
    import os
    import tempfile

    from calibkit.clitools import print_table
    from daemon.formats.c3dio import write_points_csv

    rows = []
    short_frames = 10
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    # bytecode cached as on any installed machine (pip compiles it; an editable install
    # writes it on the first run): a shell that sets PYTHONDONTWRITEBYTECODE would
    # otherwise have every timed run compile the labeller from source (about 45 ms)
    env.pop("PYTHONDONTWRITEBYTECODE", None)
    with tempfile.TemporaryDirectory() as tmp:
        for name, subject in [(n, s) for n in ("85_02", "01_01") for s in [None, *subjects]]:
            take = read_c3d(DATA / f"{name}.c3d").select(cmu.labels)
            if subject is not None:
                from daemon.synthetic.subjects import random_subject, reproportion
                take = reproportion(take, random_subject(subject))
                name = f"{name} subject {subject}"
            csv = Path(tmp) / "points.csv"
            pts = Points.from_take(take, seed=1)
            write_points_csv(csv, pts)
            short = Path(tmp) / "short.csv"
            first = pts.frame < pts.frame.min() + short_frames
            write_points_csv(short, Points(pts.frame[first], pts.xyz_m[first]))
            label = [sys.executable, "-m", "daemon.cli", "label", "--markerset", "cmu41",
                     "--out", str(Path(tmp) / "out.c3d")]
            cpu = _cpu_best(label + [str(csv)], env, repeats)
            fixed = _cpu_best(label + [str(short)], env, repeats)
            rest = (take.n_frames - short_frames) / max(min(cpu) - min(fixed), 1e-3)
            rows.append([name, take.n_frames, round(min(cpu), 2), round(take.n_frames / min(cpu)),
                         round(take.n_frames / float(np.median(cpu))), round(min(fixed), 2),
                         round(rest)])
            print(*rows[-1], flush=True, file=sys.stderr)
    for what, cmd in (("python + numpy", [sys.executable, "-c", "import numpy"]),
                      ("label --help", [sys.executable, "-m", "daemon.cli", "label", "--help"])):
        cpu = _cpu_best(cmd, env, repeats)
        rows.append([what, "", "", "", "", round(min(cpu), 2), ""])
    print("mocapd label, cmu41, clean takes from the set alone, whole command")
    print_table(rows, ["take", "frames", "cpu_s_best", "fps_best", "fps_median",
                       f"fixed_s ({short_frames} frames)", "fps_rest"])


def _cpu_best(cmd: list[str], env: dict, repeats: int) -> list[float]:
    """User + system CPU seconds of each of `repeats` runs of a child command, after one
    untimed run (which caches the bytecode)."""
    import resource
    import subprocess

    cpu = []
    for _ in range(repeats + 1):
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        subprocess.run(cmd, check=True, env=env, capture_output=True)
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
        cpu.append(after.ru_utime - before.ru_utime + after.ru_stime - before.ru_stime)
    return cpu[1:]


if __name__ == "__main__":
    main()
