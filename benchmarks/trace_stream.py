"""Where the stream's late frames are late: every frame and camera sample timed by stage.

Why: a reload is held to one frame of delay (issue 30), but the stream with no reload at all
has frames 10-20 ms late now and then (docs/daemon.md), and a reload's window that catches
one fails. This finds what those are. The daemon runs in this process (its frame loop,
multiplexer and capture hand-over are wrapped to stamp each step); the cameras run in a
`mocapd node --sim` process over Zenoh on loopback (`--in-process`: the simulator's camera
threads in the daemon's interpreter instead). For each frame: capture -> the node's arrival
of its first and last camera (`arrival_ns`), -> the sample's push into the multiplexer
(the hop and the callback), -> the frame loop's pickup, -> its outputs; the frame loop's
own CPU time for it, and the interpreter's collections. Each late frame (above the run's
median delay by --late-ms) is put down to its first cause:

  short set    a camera's frame was missing: the set waited for it to the deadline
  hop          a camera's frame reached the multiplexer late (node, Zenoh or callback)
  loop busy    the set was complete but the frame loop was still on other work
  interpreter  the frame loop's wall time for the frame exceeded its CPU time (it waited
               for the interpreter lock or a core)
  work         the frame's own CPU time
  collection   a garbage collection overlapped it

Usage: python benchmarks/trace_stream.py [--seconds 40] [--fps 120] [--realtime]
                                          [--in-process] [--late-ms 4] [--repeats 1]
"""

from __future__ import annotations

import argparse
import gc
import os
import socket
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from daemon.config.mocapd import load_config  # noqa: E402
from daemon.service.daemon import Daemon  # noqa: E402

CAUSES = ("short set", "hop", "loop busy", "interpreter", "work", "collection", "other")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Recorder:
    """The stamps, appended from the daemon's threads (list.append holds the lock)."""

    def __init__(self) -> None:
        self.frames, self.pushes, self.procs, self.gcs = [], [], [], []
        self._gc_start = 0

    def on_gc(self, phase: str, info: dict) -> None:
        if phase == "start":
            self._gc_start = time.monotonic_ns()
        else:
            self.gcs.append((self._gc_start, time.monotonic_ns(), info["generation"]))

    def wrap(self, d: Daemon) -> None:
        """Stamp the daemon's pushes, frames and outputs from now on."""
        rec, p = self, d.pipeline

        def push_from(orig):
            def push(sample):
                t0 = time.monotonic_ns()
                orig(sample)
                rec.pushes.append((sample.arrival_ns, t0))
            return push
        for cap in d.captures:  # a plain function: the node hub then pushes one by one
            cap.push = push_from(cap.push)
        process = p.process

        def timed(fs):
            t0, c0 = time.monotonic_ns(), time.thread_time_ns()
            r = process(fs)
            rec.procs.append((fs.index, t0, time.monotonic_ns(), time.thread_time_ns() - c0))
            return r
        p.process = timed

        def hook(r):
            arr = [s.arrival_ns for s in r.samples] or [r.arrival_ns]
            rec.frames.append((r.frame, r.t_ns, min(arr), max(arr), r.pickup_ns,
                               r.published_ns, len(r.samples)))
        p.hooks.append(hook)


def run_once(args) -> dict:
    port, rec = free_port(), Recorder()
    sink = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)  # the UDP output's reader
    sink.bind(("127.0.0.1", 0))
    with tempfile.TemporaryDirectory() as tmp:
        cfg_path, rt = Path(tmp) / "mocapd.toml", Path(tmp) / "rt"
        text = f"[sim]\nfps = {args.fps}\ncameras = {args.cameras}\n"
        if not args.in_process:
            text += (f'[zenoh]\nrig = "trace"\nlisten = ["tcp/127.0.0.1:{port}"]\n'
                     'cameras = "announced"\n')
        cfg_path.write_text(text + f'[[udp]]\naddress = "127.0.0.1:{sink.getsockname()[1]}"\n')
        extra = {"realtime_priority": 10} if args.realtime else {}
        d = Daemon(replace(load_config(cfg_path), runtime_dir=rt, **extra),
                   extend=lambda c: replace(c, runtime_dir=rt))
        gc.callbacks.append(rec.on_gc)
        th = threading.Thread(target=d.run, kwargs={"duration_s": args.seconds + 120},
                              daemon=True)
        th.start()
        node = None
        if not args.in_process:
            node = subprocess.Popen(
                [sys.executable, "-m", "daemon.cli", "node", "--sim", "--sim-cameras",
                 str(args.cameras), "--sim-fps", str(args.fps), "--cameras",
                 f"0-{args.cameras - 1}", "--name", "n0", "--rig", "trace", "--connect",
                 f"tcp/127.0.0.1:{port}", *(["--realtime"] if args.realtime else [])],
                cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        try:
            end = time.monotonic() + 300
            while getattr(d, "pipeline", None) is None or d.pipeline.stats.frames < 2 * args.fps:
                if time.monotonic() > end or not th.is_alive():
                    raise SystemExit("trace_stream: the daemon did not start tracking")
                time.sleep(0.1)
            rec.wrap(d)
            time.sleep(args.seconds)
        finally:
            d.stop_event.set()
            th.join(30)
            gc.callbacks.remove(rec.on_gc)
            if node is not None:
                node.terminate()
                node.wait(30)
            sink.close()
    return {"frames": np.array(rec.frames, np.int64), "pushes": np.array(rec.pushes, np.int64),
            "procs": np.array(rec.procs, np.int64), "gcs": rec.gcs, "cameras": args.cameras,
            "load": os.getloadavg()[0]}


def causes(run: dict, late_ms: float) -> tuple[dict, dict]:
    """The stage figures (ms: median, p99, max) and the late frames counted by cause."""
    F, P, U = run["frames"], run["procs"], run["pushes"]
    idx, t, a0, a1, pick, pub, n = F.T
    delay = (pub - t) / 1e6
    med = np.median(delay)
    order = np.argsort(U[:, 0])
    arr_sorted, push_sorted = U[order, 0], U[order, 1]
    proc = {int(r[0]): r for r in P}
    stages = {"capture -> node's first arrival": (a0 - t) / 1e6,
              "first -> last camera (node)": (a1 - a0) / 1e6,
              "node's last arrival -> pickup": (pick - a1) / 1e6,
              "pickup -> outputs": (pub - pick) / 1e6,
              "capture -> outputs (minus median)": delay - med}
    figures = {k: (np.median(v), np.percentile(v, 99), v.max()) for k, v in stages.items()}
    late = np.flatnonzero(delay - med > late_ms)
    counts = dict.fromkeys(CAUSES, 0)
    for i in late:
        lo, hi = np.searchsorted(arr_sorted, [a0[i], a1[i] + 1])
        hops = (push_sorted[lo:hi] - arr_sorted[lo:hi]) / 1e6
        last_push = push_sorted[lo:hi].max() if hi > lo else a1[i]
        r = proc.get(int(idx[i]))
        wall = (r[2] - r[1]) / 1e6 if r is not None else 0.0
        cpu = r[3] / 1e6 if r is not None else 0.0
        overlap = any(g0 < pub[i] and g1 > t[i] and (g1 - g0) > 1e6 for g0, g1, _ in run["gcs"])
        if n[i] < run["cameras"]:
            cause = "short set"
        elif overlap:
            cause = "collection"
        elif len(hops) and hops.max() > late_ms / 2:
            cause = "hop"
        elif (pick[i] - last_push) / 1e6 > late_ms / 2:
            cause = "loop busy"
        elif wall - cpu > late_ms / 2:
            cause = "interpreter"
        elif cpu > late_ms / 2:
            cause = "work"
        else:
            cause = "other"
        counts[cause] += 1
    return figures, {"frames": len(F), "late": len(late), **counts}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=40.0)
    ap.add_argument("--fps", type=float, default=120.0)
    ap.add_argument("--cameras", type=int, default=8)
    ap.add_argument("--realtime", action="store_true",
                    help="the daemon's threads and the node under SCHED_RR (as --realtime)")
    ap.add_argument("--in-process", action="store_true",
                    help="the simulated cameras' threads in the daemon's process")
    ap.add_argument("--late-ms", type=float, default=4.0,
                    help="a frame is late this far above the run's median delay")
    ap.add_argument("--repeats", type=int, default=1)
    args = ap.parse_args()
    if args.seconds <= 0 or args.repeats < 1 or not 2 <= args.cameras <= 32:
        raise SystemExit("trace_stream: --seconds > 0, --repeats >= 1, --cameras 2-32")
    load0 = os.getloadavg()[0]
    for k in range(args.repeats):
        run = run_once(args)
        figures, counts = causes(run, args.late_ms)
        where = "in the daemon's process" if args.in_process else "in a node process"
        print(f"\nrun {k + 1}: {counts['frames']} frames, {args.cameras} cameras {where} at "
              f"{args.fps:g} fps, {'real-time' if args.realtime else 'normal'} scheduling, "
              f"load {load0:.1f} -> {run['load']:.1f}")
        print("| stage | median ms | p99 | max |\n| --- | --- | --- | --- |")
        for name, (m, p99, mx) in figures.items():
            print(f"| {name} | {m:.2f} | {p99:.2f} | {mx:.2f} |")
        print(f"late frames (> {args.late_ms:g} ms above the median): {counts['late']}; "
              + ", ".join(f"{c} {counts[c]}" for c in CAUSES if counts[c]))


if __name__ == "__main__":
    main()
