"""What the node -> daemon hop costs on this machine, without the daemon: the nodes'
blobs into a bare Python subscriber that only decodes them (docs/nodes.md, "Where the
median hop goes").

Cases, each with the same subscriber (this process, real-time scheduling as the daemon):

- nodes: four `mocapd node --sim` processes of 8 cameras each, as bench_nodes runs them
  (clocks true, so the subscriber reads their send times directly);
- publishers, apart: four processes publishing through the node's own code
  (`CapturePublisher`, the node's Zenoh settings, real-time scheduling), 8 cameras each,
  frames 0.1-0.5 ms after each 240 Hz trigger as the simulated cameras' are, each process
  on its own trigger phase (a quarter period apart);
- publishers, together: the same with every process on the same triggers, as a rig's
  cameras are;
- sim cameras: the node's simulated cameras (`SimNodeCapture` serving `SimCamera`s, on
  the rig's triggers) through the same publisher, without the rest of a node.

The median of the runs' medians per case, and its ratio to "publishers, apart". If the
"together" case costs what the nodes do, the hop is the processes' wake-ups landing at
once on the shared cores, not the node's code.

    python benchmarks/bench_node_link.py [--seconds 12] [--repeats 2]
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from bench_nodes import free_port  # noqa: E402 - a sibling script: this folder is on the path

ENV = dict(os.environ, PYTHONPATH=str(ROOT))
RIG = "linkbench"
FPS = 240.0
CAMERAS = 8  # per process
PROCESSES = 4


def node_publishers(port: int, k: int, names: list[str]):
    """A Zenoh session and a node's publisher per camera name, set up as `mocapd node`
    sets them up (its switch interval, real-time scheduling, Zenoh settings)."""
    from daemon.nodes.node import CapturePublisher, NodeTime
    from daemon.process.realtime import raise_priority
    from daemon.publish.zenoh_session import ZenohSettings

    sys.setswitchinterval(1e-4)
    raise_priority(10)  # before the session: its threads inherit it
    session = ZenohSettings(RIG, (), (f"tcp/127.0.0.1:{port}",)).open()
    return session, [CapturePublisher(session, f"mocap/{RIG}/{name}/blobs", k, NodeTime())
                     for name in names]


def publisher(port: int, k: int, seconds: float, together: bool) -> None:
    """One publishing process: CAMERAS cameras' blobs through the node's own publisher."""
    from daemon.capture.sources import CameraSample, fine_timer_slack

    session, pubs = node_publishers(port, k, [f"p{k}c{i}" for i in range(CAMERAS)])
    fine_timer_slack()
    rng = np.random.default_rng(k)
    transfer = rng.uniform(100e3, 500e3, CAMERAS)
    uv = rng.random((12, 2)) * 1000
    area, peak = np.full(12, 12.0), np.full(12, 200.0)
    period = 1e9 / FPS
    time.sleep(1.0)
    t0 = int(np.ceil(time.monotonic_ns() / period) * period)  # the machine's trigger grid
    if not together:
        t0 += round(k * period / PROCESSES)
    g = 0
    while time.monotonic_ns() - t0 < seconds * 1e9:
        g += 1
        dues = sorted((t0 + g * period + transfer[i] + rng.exponential(50e3), i)
                      for i in range(CAMERAS))
        for due, i in dues:
            wait = due - time.monotonic_ns()
            if wait > 0:
                time.sleep(wait * 1e-9)
            now = time.monotonic_ns()
            pubs[i](CameraSample(i, g, now, now, uv, area, peak, now, g))
    session.close()


def sim_publisher(port: int, k: int, seconds: float) -> None:
    """One publishing process: the simulated cameras a node serves, without the node."""
    from dataclasses import replace

    from daemon.config.mocapd import SimConfig
    from daemon.nodes.settings import NodeConfig
    from daemon.synthetic.node_sim import SimNodeCapture, sim_sources

    first = CAMERAS * k
    cfg = replace(NodeConfig(), sim=replace(SimConfig(), cameras=CAMERAS * PROCESSES),
                  sim_cameras=tuple(f"cam{i}" for i in range(first, first + CAMERAS)))
    sources = sim_sources(cfg)
    session, pushes = node_publishers(port, k, [src.name for src in sources])
    capture = SimNodeCapture(sources, pushes)
    capture.start()
    time.sleep(seconds)
    capture.stop()
    session.close()


def subscribe(port: int, seconds: float, start) -> np.ndarray:
    """Hop (ms) of every message that came within `seconds`, the first third left out."""
    import zenoh

    from daemon.publish import zenoh_wire as wire
    from daemon.publish.zenoh_session import ZenohSettings

    hops: list[int] = []

    def on_blobs(sample) -> None:
        now = time.monotonic_ns()
        hops.append(now - wire.decode_blobs(sample.payload.to_bytes()).sent_ns)

    session = ZenohSettings(RIG, (f"tcp/127.0.0.1:{port}",), ()).open()
    session.declare_subscriber(f"mocap/{RIG}/*/blobs", zenoh.handlers.Callback(on_blobs))
    procs = start()
    try:
        time.sleep(seconds)
    finally:
        for p in procs:
            p.terminate()
        for p in procs:
            p.wait(30)
        session.close()
    h = np.asarray(hops[len(hops) // 3:], dtype=np.float64) * 1e-6
    if len(h) < 100:
        raise SystemExit(f"only {len(h)} messages came: is Zenoh working on loopback?")
    return h


def run_case(case: str, seconds: float) -> np.ndarray:
    port = free_port()
    if case == "sim cameras":
        def start():
            return [subprocess.Popen(
                [sys.executable, __file__, "--sim-publisher", str(k), "--port", str(port),
                 "--seconds", str(seconds + 30)], cwd=ROOT, env=ENV)
                for k in range(PROCESSES)]
        wait = seconds + 8  # the simulated scene is built first
    elif case == "nodes":
        def start():
            return [subprocess.Popen(
                [sys.executable, "-m", "daemon.cli", "node", "--sim", "--sim-cameras",
                 str(CAMERAS * PROCESSES), "--cameras",
                 f"{CAMERAS * k}-{CAMERAS * k + CAMERAS - 1}", "--name", f"n{k}", "--rig", RIG,
                 "--connect", f"tcp/127.0.0.1:{port}", "--publish", "cameras",
                 "--duration", str(seconds + 30), "--realtime"], cwd=ROOT, env=ENV,
                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
                for k in range(PROCESSES)]
        wait = seconds + 8  # the nodes build their simulated scene first
    else:
        together = case.endswith("together")

        def start():
            return [subprocess.Popen(
                [sys.executable, __file__, "--publisher", str(k), "--port", str(port),
                 "--seconds", str(seconds + 30)] + (["--together"] if together else []),
                cwd=ROOT, env=ENV) for k in range(PROCESSES)]
        wait = seconds + 1
    return subscribe(port, wait, start)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seconds", type=float, default=12.0)
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--publisher", type=int, default=None, help=argparse.SUPPRESS)
    ap.add_argument("--sim-publisher", type=int, default=None, help=argparse.SUPPRESS)
    ap.add_argument("--port", type=int, default=0, help=argparse.SUPPRESS)
    ap.add_argument("--together", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.publisher is not None:
        return publisher(args.port, args.publisher, args.seconds, args.together)
    if args.sim_publisher is not None:
        return sim_publisher(args.port, args.sim_publisher, args.seconds)

    from calibkit.clitools import print_table
    from daemon.process.realtime import raise_priority, restore_normal

    sys.setswitchinterval(1e-4)  # as the daemon's hub
    print(f"subscriber: {raise_priority(10)}", file=sys.stderr)
    cases = ["publishers, apart", "publishers, together", "sim cameras", "nodes"]
    got: dict[str, list] = {c: [] for c in cases}
    try:
        for r in range(args.repeats):  # interleaved: the machine's drift hits every case
            for c in cases:
                h = run_case(c, args.seconds)
                got[c].append(np.percentile(h, [50, 90, 99]))
                print(f"run {r + 1} {c}: {np.round(got[c][-1], 3)}", file=sys.stderr)
    finally:
        restore_normal()
    base = float(np.median([g[0] for g in got["publishers, apart"]]))
    rows = []
    for c in cases:
        m = np.median(np.array(got[c]), axis=0)
        rows.append([c, f"{m[0]:.3f}", f"{m[1]:.3f}", f"{m[2]:.3f}", f"{m[0] / base:.2f}"])
    print(f"node -> bare subscriber, {PROCESSES} processes x {CAMERAS} cameras at {FPS:.0f} "
          f"fps, median of {args.repeats} runs (ms)")
    print_table(rows, ["case", "median", "p90", "p99", "median / apart"])


if __name__ == "__main__":
    main()
