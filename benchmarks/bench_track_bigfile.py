"""Peak memory and time of `mocapd track` on big points CSVs: issue 29's "1 GB in < 1 GB RSS".

For each --mb size, benchmarks/gen_points_csv.py writes a points CSV of that size under
--dir (bench_track's scene: 10 rigid bodies of 4-5 markers at 120 Hz, 0.5 mm noise, 5 %
hidden in spans, 2 strays a frame, in frame order), then each row below runs in a child
process of its own, timed by wall clock and by the child's CPU time, its peak RSS its own
(os.wait4's ru_maxrss): the memory a user sees, not this script's.
  - mocapd track: the whole command, the take tracked and written a window at a time
    (daemon/analysis/track_stream.py);
  - read only: the file streamed into the spool `mocapd track` reads it into, nothing
    tracked (the floor: parsing the text);
  - before (with --before DIR, a checkout of the tree before windows, e.g. `git worktree
    add /tmp/before 17d03d0`): the same command from that tree, the whole take in memory;
    only on files up to --before-max-mb (it needs several times the file).
Each command's stderr is searched for numba's compile notice ("compiling the ... kernels"):
after `mocapd build-kernels` the count must be 0. The generated files are deleted after.

    python benchmarks/bench_track_bigfile.py --mb 100 1000 [--repeats 1] [--before DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
READ_ONLY = ("import sys; from daemon.formats.points_csv import stream_points_csv; "
             "from daemon.analysis.track_stream import Spool; s = Spool(sys.argv[2]); "
             "stream_points_csv(sys.argv[1], s); s.finish(); print(s.n, len(s.frames))")
NOTICE = "compiling the "


def child(argv: list[str], tree: Path = ROOT) -> tuple[float, float, float, str]:
    """(wall s, CPU s, peak RSS MB, stderr) of one child process running the code of
    `tree`; stderr goes to a file so a long progress output cannot fill a pipe."""
    env = dict(os.environ, PYTHONPATH=str(tree))
    with tempfile.TemporaryFile() as err:
        start = time.perf_counter()
        proc = subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=err, env=env,
                                cwd=tree)
        _, status, usage = os.wait4(proc.pid, 0)
        wall = time.perf_counter() - start
        err.seek(0)
        text = err.read().decode(errors="replace")
    if os.waitstatus_to_exitcode(status) != 0:
        raise SystemExit(f"{' '.join(map(str, argv[:5]))} ... failed: {text[-800:]}")
    return wall, usage.ru_utime + usage.ru_stime, usage.ru_maxrss / 1024.0, text


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--mb", type=float, nargs="+", default=[100.0, 1000.0])
    parser.add_argument("--repeats", type=int, default=1)
    parser.add_argument("--dir", type=Path, default=Path(tempfile.gettempdir()))
    parser.add_argument("--before", type=Path, default=None)
    parser.add_argument("--before-max-mb", type=float, default=150.0)
    args = parser.parse_args()
    py = sys.executable
    print(f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores at the start; "
          f"median (worst) of {args.repeats}")
    header = ["file MB", "what", "frames", "points", "peak RSS MB", "RSS / file",
              "wall s", "CPU s", "compiles"]
    rows = []
    for mb in args.mb:
        work = Path(tempfile.mkdtemp(prefix="bench_bigfile_", dir=args.dir))
        path = work / f"points_{mb:g}mb.csv"
        try:
            subprocess.run([py, str(ROOT / "benchmarks" / "gen_points_csv.py"), "--mb",
                            str(mb), "--out", str(path)], check=True, stdout=subprocess.DEVNULL,
                           env=dict(os.environ, PYTHONPATH=str(ROOT)))
            size = path.stat().st_size / 1e6
            bodies = work / f"{path.name}.bodies.toml"
            track = ["track", str(path), "--bodies", str(bodies), "--out",
                     str(work / "poses.csv"), "--json", str(work / "figs.json")]
            cases = {"mocapd track (windows)": ([py, "-m", "daemon.cli", *track], ROOT),
                     "read only (spool)": ([py, "-c", READ_ONLY, str(path), str(work)], ROOT)}
            if args.before is not None and mb <= args.before_max_mb:
                cases["before: whole take"] = ([py, "-m", "daemon.cli", *track],
                                               args.before.resolve())
            for name, (argv, tree) in cases.items():
                runs, compiles = [], 0
                for _ in range(args.repeats):
                    wall, cpu, rss, err = child(argv, tree)
                    runs.append((wall, cpu, rss))
                    compiles += sum(ln.startswith(NOTICE) for ln in err.splitlines())
                frames = points = ""
                if name != "read only (spool)":
                    figs = json.loads((work / "figs.json").read_text())
                    frames = figs["frames"]
                    points = figs["input"].get("bad_rows", {}).get("rows", "")
                    (work / "figs.json").unlink()
                r = np.array(runs)
                med, worst = np.median(r, axis=0), r.max(axis=0)
                rows.append([f"{size:.0f}", name, frames, points,
                             f"{med[2]:.0f} ({worst[2]:.0f})", f"{med[2] / size:.2f}",
                             f"{med[0]:.1f} ({worst[0]:.1f})", f"{med[1]:.1f} ({worst[1]:.1f})",
                             compiles])
                print(" | ".join(map(str, rows[-1])), flush=True)
        finally:
            for p in work.iterdir():
                p.unlink()
            work.rmdir()
    print(f"load average {os.getloadavg()[0]:.1f} at the end")
    print("| " + " | ".join(header) + " |")
    print("|" + " --- |" * len(header))
    for row in rows:
        print("| " + " | ".join(map(str, row)) + " |")


if __name__ == "__main__":
    main()
