"""The whole daemon's CPU time per camera-frame with simulated cameras, by thread and stage.

Why: `bench_nodes.py` divides the daemon process's CPU time by the camera-frames it took,
which with `--sim` counts the simulator's own work (its cameras rendering blobs in the
capture threads, the truth scorer run by the frame loop while it waits) as the daemon's.
A real deployment pays none of that. This runs the daemon (`Daemon.run`, as `mocapd start
--sim --realtime` does) inside this process and measures, over a steady window, the CPU
time of every thread (/proc/self/task/TID/stat, Python threads by name, native ones such
as Zenoh's by their kernel name) and, inside the threads, the stages by
`time.thread_time_ns` around the daemon's own methods:

- pairing: `Multiplexer.push` (in the capture threads) and `Multiplexer.next` (frame loop);
- tracker, bodies, labelling, outputs, rest: `Pipeline.process`'s parts (outputs = the
  publishers' `submit` and the hooks; rest = gathering the set's blobs, the stats...);
- scorer (simulator only): the idle hooks, i.e. the truth scorers;
- simulated cameras (simulator only): the capture threads' time outside `push`;
- loop other: the frame loop's thread outside the stages above (its waits, ticks).

"daemon" is what a deployment pays (everything but the simulator's two rows); "process"
is what `bench_nodes.py` reports. Each configuration runs `--repeats` times in this process
and the median is printed.

    python benchmarks/bench_frame_cost.py [--cameras 8 32] [--seconds 6] [--repeats 1]
                                          [--profile]
"""

from __future__ import annotations

import argparse
import cProfile
import os
import pstats
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from calibkit.clitools import print_table

TICK_S = 1.0 / os.sysconf("SC_CLK_TCK")


def task_cpu_s() -> dict[int, tuple[str, float]]:
    """tid -> (kernel name, CPU seconds) of every thread of this process."""
    out = {}
    for d in Path("/proc/self/task").iterdir():
        try:
            stat = (d / "stat").read_text()
        except OSError:
            continue
        name = stat[stat.index("(") + 1:stat.rindex(")")]
        f = stat.rpartition(")")[2].split()
        out[int(d.name)] = (name, (int(f[11]) + int(f[12])) * TICK_S)
    return out


class Clock:
    """Thread CPU time spent inside wrapped methods, by stage (exclusive of nested stages)."""

    def __init__(self) -> None:
        self.ns: dict[str, int] = {}
        self._local = threading.local()
        self.lock = threading.Lock()

    def wrap(self, owner, attr: str, stage: str) -> None:
        inner = getattr(owner, attr)
        clock = self

        def timed(*a, **kw):
            stack = getattr(clock._local, "stack", None)
            if stack is None:
                stack = clock._local.stack = []
            t0 = time.thread_time_ns()
            stack.append(0)
            try:
                return inner(*a, **kw)
            finally:
                spent = time.thread_time_ns() - t0
                nested = stack.pop()
                if stack:
                    stack[-1] += spent
                with clock.lock:
                    clock.ns[stage] = clock.ns.get(stage, 0) + spent - nested

        setattr(owner, attr, timed)
        return inner


def instrument(daemon, clock: Clock) -> None:
    """Wrap the daemon's parts once it is set up (called from the multiplexer's creation)."""
    p = daemon.pipeline
    clock.wrap(daemon.mux, "push", "pairing (push)")
    clock.wrap(daemon.mux, "next", "pairing (next)")
    clock.wrap(p, "process", "frame set: rest")
    clock.wrap(p.tracker, "update", "tracker")
    clock.wrap(p.rigid, "update", "bodies")
    clock.wrap(p.rigid, "hidden_markers", "bodies")
    clock.wrap(p.tracker, "place", "tracker")
    clock.wrap(p.stats, "add", "frame set: rest")
    if p.labeller is not None:
        p.labeller = _timed_call(clock, p.labeller, "labelling")
    for pub in p.publishers:
        clock.wrap(pub, "submit", "outputs")
    p.hooks = [_timed_call(clock, h, "outputs") for h in p.hooks]
    p.idle_hooks = [_timed_call(clock, h, "scorer (sim only)") for h in p.idle_hooks]


def _timed_call(clock: Clock, fn, stage: str):
    holder = type("H", (), {"__call__": lambda self, *a, **kw: fn(*a, **kw)})()
    clock.wrap(holder, "__call__", stage)
    return holder.__call__


def run_once(cameras: int, seconds: float, warmup_s: float, profile: bool) -> dict:
    from daemon.capture import multiplexer as mux_mod
    from daemon.config.mocapd import load_config
    from daemon.service import daemon as daemon_mod

    tmp = Path(tempfile.mkdtemp(prefix="frame-cost-"))
    conf = tmp / "sim.toml"
    conf.write_text(f'runtime_dir = "{tmp / "run"}"\n[sim]\ncameras = {cameras}\nbodies = 3\n')
    from daemon.commands.start_run import StartOverrides

    cfg = StartOverrides(realtime=True).apply(load_config(conf))
    d = daemon_mod.Daemon(cfg, None)
    clock = Clock()
    real_mux = mux_mod.Multiplexer

    # the daemon builds its multiplexer after its pipeline and capture threads: the place
    # to wrap them all before the first frame
    def make_mux(*a, **kw):
        m = real_mux(*a, **kw)
        d.mux = m
        instrument(d, clock)
        if prof is not None:  # the frame loop's thread from here on, setup left out
            prof.enable()
        ready.set()
        return d.mux

    daemon_mod.Multiplexer = make_mux
    window: dict = {}
    prof = cProfile.Profile(time.thread_time_ns, 1e-9) if profile else None  # CPU time
    main_tid = threading.get_native_id()

    ready = threading.Event()

    def sample():
        ready.wait(300)
        time.sleep(warmup_s)
        frames0 = sum(c.frames for c in d.captures)
        cpu0, st0 = task_cpu_s(), dict(clock.ns)
        sets0 = d.pipeline.stats.frames
        time.sleep(seconds)
        frames1 = sum(c.frames for c in d.captures)
        cpu1, st1 = task_cpu_s(), dict(clock.ns)
        names = {t.native_id: t.name for t in threading.enumerate() if t.native_id}
        window.update(names=names, camera_frames=frames1 - frames0,
                      sets=d.pipeline.stats.frames - sets0, cpu0=cpu0, cpu1=cpu1, st0=st0, st1=st1)
        d.stop_event.set()

    sampler = threading.Thread(target=sample, name="bench-sampler", daemon=True)
    sampler.start()
    try:
        d.run(None, warmup_s + seconds + 120)
    finally:
        if prof is not None:
            prof.disable()
        daemon_mod.Multiplexer = real_mux
    sampler.join()
    threads = dict(window["names"])
    threads[main_tid] = "frame loop"
    by_thread: dict[str, float] = {}
    for tid, (kname, c1) in window["cpu1"].items():
        c0 = window["cpu0"].get(tid, (kname, 0.0))[1]
        name = threads.get(tid) or f"native: {kname}"
        if name.startswith("cam-"):
            name = "capture threads (cam-*)"
        elif name == "bench-sampler":
            continue
        by_thread[name] = by_thread.get(name, 0.0) + (c1 - c0)
    stages = {k: (window["st1"].get(k, 0) - window["st0"].get(k, 0)) * 1e-9
              for k in window["st1"]}
    n = max(window["camera_frames"], 1)
    per = {k: v * 1e6 / n for k, v in stages.items()}
    threads_us = {k: v * 1e6 / n for k, v in by_thread.items()}
    cams_us = threads_us.get("capture threads (cam-*)", 0.0)
    per["simulated cameras (sim only)"] = cams_us - per.get("pairing (push)", 0.0)
    loop_us = threads_us.get("frame loop", 0.0)
    in_loop = sum(v for k, v in per.items()
                  if k not in ("pairing (push)", "simulated cameras (sim only)"))
    per["loop other"] = loop_us - in_loop
    process_us = sum(threads_us.values())
    sim_us = per["simulated cameras (sim only)"] + per.get("scorer (sim only)", 0.0)
    return {"per": per, "threads": threads_us, "process": process_us,
            "daemon": process_us - sim_us, "sets": window["sets"],
            "camera_frames": window["camera_frames"], "seconds": seconds, "prof": prof}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cameras", type=int, nargs="+", default=[8, 32])
    ap.add_argument("--seconds", type=float, default=6.0)
    ap.add_argument("--warmup", type=float, default=4.0)
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--profile", action="store_true",
                    help="also print cProfile's top functions of the frame loop (largest run)")
    args = ap.parse_args()
    results = {}
    for cameras in args.cameras:
        results[cameras] = [run_once(cameras, args.seconds, args.warmup, False)
                            for _ in range(args.repeats)]
    rows_keys: list[str] = []
    for runs in results.values():
        for r in runs:
            for k in sorted(r["per"]) + [f"thread: {t}" for t in sorted(r["threads"])]:
                if k not in rows_keys:
                    rows_keys.append(k)

    def med(runs, key):
        vals = []
        for r in runs:
            if key.startswith("thread: "):
                vals.append(r["threads"].get(key[8:], 0.0))
            else:
                vals.append(r[key] if key in r else r["per"].get(key, 0.0))
        return float(np.median(vals))

    rows = []
    for key in rows_keys + ["process", "daemon"]:
        rows.append([key, *(f"{med(runs, key):.1f}" for runs in results.values())])
    rate = [np.median([r["sets"] / r["seconds"] for r in runs]) for runs in results.values()]
    rows.append(["frame sets a second", *(f"{x:.0f}" for x in rate)])
    print(f"CPU us per camera-frame, median of {args.repeats} run(s) of {args.seconds:.0f} s "
          f"after {args.warmup:.0f} s; load {os.getloadavg()[0]:.1f}, {os.cpu_count()} cores")
    print_table(rows, ["stage / thread", *(f"{c} cameras" for c in results)])
    if args.profile:
        # a run of its own: the profiler slows the frame loop several times over
        prof = run_once(max(results), args.seconds, args.warmup, True)["prof"]
        print(f"\n--- frame loop's CPU time (a separate, profiled run), {max(results)} cameras:"
              " top functions by own time")
        pstats.Stats(prof).sort_stats("tottime").print_stats(20)


if __name__ == "__main__":
    main()
