"""How long a rendered simulated intrinsic calibration takes per camera, the figure
`calibkit intrinsic --help` quotes (issue 31).

Each case is one `calibkit intrinsic` run of one camera in a child process (wall time, and
CPU time of the process and its threads from os.wait4, which the machine's load disturbs
less), --repeats times; the medians are printed. Cases: the rendered --sim capture (the
default), --display --sim (the monitor path with the display code drawing the simulated
monitor), and the baseline in the same run, --sim --no-render (no image at all; what is
left is start-up, imports and the solve). Every case also prints the focal length error
against the simulator's truth, so a faster path that measured worse would show.

    python benchmarks/bench_intrinsic_render.py [--repeats 3] [--views 6] [--size 640x480]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

RUN = "import sys; sys.argv = {argv!r}; from calibkit.cli import main; main()"

CASES = [
    ("--sim --no-render (baseline)", ["--sim", "--no-render"]),
    ("--sim (rendered, the default)", ["--sim"]),
    ("--display --sim", ["--display", "--sim"]),
]


def _child(args: list[str], workdir: Path) -> tuple[float, float, float]:
    """(wall s, CPU s, |fx error| %) of one run; a failure stops the benchmark."""
    out = workdir / "fig.json"
    argv = ["calibkit", "intrinsic", *args, "--json", str(out)]
    start = time.perf_counter()
    proc = subprocess.Popen([sys.executable, "-c", RUN.format(argv=argv)],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, cwd=workdir)
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - start
    err = proc.stderr.read().decode(errors="replace")
    proc.stderr.close()
    if os.waitstatus_to_exitcode(status) != 0:
        raise SystemExit(f"{' '.join(argv)} failed:\n{err}")
    error = json.loads(out.read_text())["error"]["fx_rel"]
    return wall, usage.ru_utime + usage.ru_stime, abs(100.0 * error)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--views", type=int, default=6)
    parser.add_argument("--size", default="640x480")
    opts = parser.parse_args()
    common = ["--views", str(opts.views), "--size", opts.size]
    print(f"load average {os.getloadavg()[0]:.1f} {os.getloadavg()[1]:.1f} on "
          f"{os.cpu_count()} cores; one camera, {opts.views} views, {opts.size}, "
          f"medians of {opts.repeats}")
    print(f"{'case':32} {'wall s':>8} {'CPU s':>8} {'|fx err| %':>11}")
    with tempfile.TemporaryDirectory() as tmp:
        for label, args in CASES:
            runs = [_child([*args, *common], Path(tmp)) for _ in range(opts.repeats)]
            wall, cpu, err = (statistics.median(r[k] for r in runs) for k in range(3))
            print(f"{label:32} {wall:8.1f} {cpu:8.1f} {err:11.4f}")


if __name__ == "__main__":
    main()
