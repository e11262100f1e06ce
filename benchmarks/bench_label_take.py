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
--breakdown: where the command's CPU goes, in this process (imports not counted): the
marker set read, the CSV read, label_take split into the start window's assignment (the
set alone: the fixed part) and the rest, and the C3D written; median of the repeats.

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
    ap.add_argument("--breakdown", action="store_true")
    ap.add_argument("--against", type=Path, default=None,
                    help="(--command) another version's tree: its runs interleaved with ours")
    args = ap.parse_args()
    warnings.simplefilter("ignore")
    cmu = open_set("cmu41")
    if args.breakdown:
        return breakdown_table(cmu, args.repeats, [int(v) for v in args.subjects.split(",")
                                                   if v])
    if args.command:
        seeds = [int(v) for v in args.subjects.split(",") if v]
        return command_table(cmu, args.repeats, seeds, args.against)
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


def _take_files(cmu, subjects, folder: Path):
    """The shared takes, and each as performed by the given subjects: (name, its points
    written to folder/points.csv, the points)."""
    from daemon.formats.c3dio import write_points_csv

    for name, subject in [(n, s) for n in ("85_02", "01_01") for s in [None, *subjects]]:
        take = read_c3d(DATA / f"{name}.c3d").select(cmu.labels)
        if subject is not None:
            from daemon.synthetic.subjects import random_subject, reproportion
            take = reproportion(take, random_subject(subject))
            name = f"{name} subject {subject}"
        csv = folder / "points.csv"
        pts = Points.from_take(take, seed=1)
        write_points_csv(csv, pts)
        yield name, take, csv, pts


def command_table(cmu, repeats: int, subjects: list[int] | None = None,
                  against: Path | None = None) -> None:
    """The whole command, start-up included, from the set alone, in child processes. With
    `against` (another version's tree) each run of ours is followed by one of that version
    on the same points (the same load for both), a row each."""
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
        for name, take, csv, pts in _take_files(cmu, subjects, Path(tmp)):
            short = Path(tmp) / "short.csv"
            first = pts.frame < pts.frame.min() + short_frames
            write_points_csv(short, Points(pts.frame[first], pts.xyz_m[first]))
            label = [sys.executable, "-m", "daemon.cli", "label", "--markerset", "cmu41",
                     "--out", str(Path(tmp) / "out.c3d")]
            trees = [("", ROOT)] + ([(" (against)", against.resolve())] if against else [])
            envs = [dict(env, PYTHONPATH=str(tree)) for _, tree in trees]
            cpus = _cpu_best(label + [str(csv)], envs, repeats)
            fixeds = _cpu_best(label + [str(short)], envs, repeats)
            for (tag, _), cpu, fixed in zip(trees, cpus, fixeds, strict=True):
                rest = (take.n_frames - short_frames) / max(min(cpu) - min(fixed), 1e-3)
                rows.append([name + tag, take.n_frames, round(min(cpu), 2),
                             round(take.n_frames / min(cpu)),
                             round(take.n_frames / float(np.median(cpu))), round(min(fixed), 2),
                             round(rest)])
                print(*rows[-1], flush=True, file=sys.stderr)
    for what, cmd in (("python + numpy", [sys.executable, "-c", "import numpy"]),
                      ("label --help", [sys.executable, "-m", "daemon.cli", "label", "--help"])):
        cpu = _cpu_best(cmd, [env], repeats)[0]
        rows.append([what, "", "", "", "", round(min(cpu), 2), ""])
    print("mocapd label, cmu41, clean takes from the set alone, whole command")
    print_table(rows, ["take", "frames", "cpu_s_best", "fps_best", "fps_median",
                       f"fixed_s ({short_frames} frames)", "fps_rest"])


def breakdown_table(cmu, repeats: int, subjects: list[int]) -> None:
    """The command's stages timed in this process (CPU seconds, median of the repeats)."""
    import tempfile

    import daemon.labelling.offline as offline
    from calibkit.clitools import print_table
    from daemon.commands.points_input import read_points_for_command
    from daemon.formats.c3dio import write_take

    spent = {"start": 0.0}
    start_fn = offline.window_start

    def timed_start(*a, **k):
        c0 = time.process_time()
        try:
            return start_fn(*a, **k)
        finally:
            spent["start"] += time.process_time() - c0

    offline.window_start = timed_start
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for name, take, csv, _pts in _take_files(cmu, subjects, Path(tmp)):
            runs = []
            for _ in range(repeats):
                c = [time.process_time()]
                ms = open_set("cmu41")
                c.append(time.process_time())
                pts, _ = read_points_for_command(csv, False)
                c.append(time.process_time())
                spent["start"] = 0.0
                out, _, _ = label_take(pts, ms, 120.0)
                c.append(time.process_time())
                write_take(Path(tmp) / "out.c3d", out)
                c.append(time.process_time())
                d = np.diff(c)
                runs.append([d[0], d[1], spent["start"], d[2] - spent["start"], d[3]])
            med = np.median(runs, axis=0)
            rows.append([name, take.n_frames, *(round(float(v), 3) for v in med),
                         round((take.n_frames - 10) / med[3])])
            print(*rows[-1], flush=True, file=sys.stderr)
    print("mocapd label's stages, cmu41, clean takes from the set alone, CPU s (median)")
    print_table(rows, ["take", "frames", "set_s", "csv_s", "start_s", "rest_s", "write_s",
                       "fps_rest"])


def _cpu_best(cmd: list[str], envs: list[dict], repeats: int) -> list[list[float]]:
    """User + system CPU seconds of each of `repeats` runs of a child command in each
    environment (the environments' runs interleaved), after one untimed run each (which
    caches the bytecode). The child runs in its PYTHONPATH's tree."""
    import resource
    import subprocess

    cpu: list[list[float]] = [[] for _ in envs]
    for _ in range(repeats + 1):
        for k, env in enumerate(envs):
            before = resource.getrusage(resource.RUSAGE_CHILDREN)
            subprocess.run(cmd, check=True, env=env, capture_output=True,
                           cwd=env.get("PYTHONPATH"))
            after = resource.getrusage(resource.RUSAGE_CHILDREN)
            cpu[k].append(after.ru_utime - before.ru_utime + after.ru_stime - before.ru_stime)
    return [c[1:] for c in cpu]


if __name__ == "__main__":
    main()
