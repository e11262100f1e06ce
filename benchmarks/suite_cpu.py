"""Where the test suite's time goes: CPU and wall time per test module, and the wait between.

Why: the suite's wall time on two workers is each worker's CPU plus the time its tests wait
on real time (a live daemon's frames, a node's clock window, a robot's drive). On a quiet
machine the waits decide the wall time; on a slow or loaded one the CPU does. pytest's
`--durations` gives wall time only; this gives both, per module and per test, so that a cut
goes where it pays.

    python benchmarks/suite_cpu.py [--top 30] [--tests 10] [-- PYTEST ARGS...]

Runs `python3 -m pytest` (the README's command, with the given arguments after `--`) with
this file as a plugin: each test's CPU is its worker's own plus that of the children it
waited for (resource.getrusage), measured around the whole test (setup, call, teardown).
A child a module fixture starts is counted at the test whose teardown reaps it; the run's
background kernel build is counted at the test that waited for it. Prints the modules by
CPU, then the tests that waited longest, and the totals.
"""

from __future__ import annotations

import argparse
import os
import resource
import subprocess
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
OUT_ENV = "SUITE_CPU_DIR"


def _cpu() -> float:
    own = resource.getrusage(resource.RUSAGE_SELF)
    kids = resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):
    """(plugin) One line per test: node id, CPU s, wall s, into the run's folder."""
    t0, c0 = time.monotonic(), _cpu()
    yield
    t1, c1 = time.monotonic(), _cpu()
    folder = os.environ.get(OUT_ENV)
    if folder:
        worker = os.environ.get("PYTEST_XDIST_WORKER", "main")
        with open(Path(folder) / f"{worker}.tsv", "a", encoding="utf-8") as f:
            f.write(f"{item.nodeid}\t{c1 - c0:.3f}\t{t1 - t0:.3f}\n")


def read_rows(folder: Path) -> list[tuple[str, float, float]]:
    rows = []
    for path in sorted(folder.glob("*.tsv")):
        for line in path.read_text(encoding="utf-8").splitlines():
            nodeid, cpu, wall = line.rsplit("\t", 2)
            rows.append((nodeid, float(cpu), float(wall)))
    return rows


def print_summary(rows: list[tuple[str, float, float]], top: int, tests: int) -> None:
    from calibkit.clitools import print_table

    per = defaultdict(lambda: [0.0, 0.0, 0])
    for nodeid, cpu, wall in rows:
        m = per[nodeid.split("::")[0]]
        m[0] += cpu
        m[1] += wall
        m[2] += 1
    mods = sorted(per.items(), key=lambda kv: -kv[1][0])[:top]
    print("CPU and wall time per test module (s), by CPU")
    print_table([[name, n, round(c, 1), round(w, 1), round(w - c, 1)]
                 for name, (c, w, n) in mods], ["module", "tests", "cpu_s", "wall_s", "wait_s"])
    waits = sorted(rows, key=lambda r: -(r[2] - r[1]))[:tests]
    print("\nThe tests that waited longest (wall - CPU, s)")
    print_table([[n, round(c, 1), round(w, 1), round(w - c, 1)] for n, c, w in waits],
                ["test", "cpu_s", "wall_s", "wait_s"])
    cpu, wall = sum(r[1] for r in rows), sum(r[2] for r in rows)
    print(f"\n{len(rows)} tests: CPU {cpu:.0f} s, wall {wall:.0f} s summed over the "
          f"workers (wait {wall - cpu:.0f} s)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--top", type=int, default=30, help="modules shown")
    ap.add_argument("--tests", type=int, default=10, help="longest-waiting tests shown")
    ap.add_argument("pytest_args", nargs="*", help="after --: passed to pytest")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="suite-cpu-") as tmp:
        env = dict(os.environ, **{OUT_ENV: tmp})
        env["PYTHONPATH"] = os.pathsep.join(
            [str(ROOT / "benchmarks"), *filter(None, [env.get("PYTHONPATH")])])
        t0 = time.monotonic()
        proc = subprocess.run([sys.executable, "-m", "pytest", "-p", "suite_cpu",
                               *args.pytest_args], cwd=ROOT, env=env)
        took = time.monotonic() - t0
        rows = read_rows(Path(tmp))
    if not rows:
        raise SystemExit(f"suite_cpu: pytest ran no test (exit {proc.returncode})")
    print_summary(rows, args.top, args.tests)
    print(f"pytest exit {proc.returncode}, {took:.0f} s wall")
    sys.exit(proc.returncode)


if __name__ == "__main__":
    main()
