"""How long `mocapd start --sim` takes to exit after SIGTERM, everything flushed.

Each run starts a daemon with a UDP output and a recording, waits until it has tracked for
a second, sends SIGTERM and times the exit; then it checks the recording reads back and the
control socket is gone. Printed: median, p99 and worst over the runs, beside the load.
Baseline in the same process: a bare `python -c "import numpy"` started and ended, the
interpreter's own cost of ending a process with a few modules loaded.

The target (issue 30): SIGTERM to exit <= 1 s, p99 of 20 stops.

    python benchmarks/bench_stop.py [--runs 20] [--json out.json]
"""

from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from calibkit.clitools import print_table, write_json
from calibkit.core.errors import UserError

ROOT = Path(__file__).resolve().parents[1]
ENV = {**os.environ, "PYTHONPATH": str(ROOT)}


def _control(rt: Path, message: dict) -> dict:
    from daemon.service.control import request

    return request(rt, message, timeout_s=10.0)


def one_stop(folder: Path, k: int) -> tuple[float, bool]:
    rt = folder / f"rt{k}"
    rec = folder / f"take{k}.mcrec"
    proc = subprocess.Popen([sys.executable, "-m", "daemon.cli", "start", "--sim",
                             "--udp", "127.0.0.1:9", "--runtime-dir", str(rt)], cwd=ROOT,
                            env=ENV, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 120
        while True:
            try:
                if _control(rt, {"cmd": "status"}).get("frames", 0) > 0:
                    break
            except UserError:  # not up yet
                pass
            if time.monotonic() > deadline or proc.poll() is not None:
                raise RuntimeError("the daemon did not start")
            time.sleep(0.1)
        _control(rt, {"cmd": "record", "path": str(rec)})
        time.sleep(1.0)
        t0 = time.monotonic()
        proc.send_signal(signal.SIGTERM)
        proc.wait(60)
        took = time.monotonic() - t0
    finally:
        if proc.poll() is None:
            proc.kill()
    from calibkit.core.recording import load_observations

    clean = (proc.returncode == 0 and not (rt / "mocapd.sock").exists()
             and len(load_observations(rec)[0].frames()) > 10)
    return took, clean


def bare_exit() -> float:
    t0 = time.monotonic()
    subprocess.run([sys.executable, "-c", "import numpy"], check=True)
    return time.monotonic() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=20)
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    load = os.getloadavg()[0]
    stops, clean, base = [], 0, []
    with tempfile.TemporaryDirectory() as tmp:
        for k in range(args.runs):
            took, ok = one_stop(Path(tmp), k)
            stops.append(took)
            clean += ok
            base.append(bare_exit())
            print(f"stop {k + 1}/{args.runs}: {took:.3f} s{'' if ok else ' (NOT clean)'}",
                  file=sys.stderr)
    s = np.array(stops)
    fig = {"runs": args.runs, "median_s": float(np.median(s)),
           "p99_s": float(np.percentile(s, 99)), "worst_s": float(s.max()),
           "clean_stops": clean, "bare_python_start_and_exit_s": float(np.median(base)),
           "load_average_at_start": load}
    print_table([["SIGTERM to exit, median (s)", fig["median_s"]],
                 ["SIGTERM to exit, p99 (s)", fig["p99_s"]],
                 ["SIGTERM to exit, worst (s)", fig["worst_s"]],
                 ["clean stops (exit 0, recording readable, socket gone)",
                  f"{clean}/{args.runs}"],
                 ["baseline: python -c 'import numpy', start to exit (s)",
                  fig["bare_python_start_and_exit_s"]],
                 ["load average at the start", load]], ["what", "value"])
    if args.json:
        write_json(args.json, fig)


if __name__ == "__main__":
    main()
