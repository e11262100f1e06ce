"""The daemon's CPU time per camera-frame, by stage, for cameras served by nodes.

Why: wall-clock rates and latencies measured on a loaded machine say little about a quiet
one, but the CPU time the daemon spends on each camera-frame does (it is what must fit
7680 times a second for 32 cameras at 240 fps). This runs the daemon's own code for
remote cameras in one thread, with no network (Zenoh's callback is called directly with
the bytes a node would have sent), and measures thread CPU time:

- decode: the wire decoder alone (daemon.publish.zenoh_wire);
- hub: + the hub's callback (node clock mapping, per-camera checks, hop figures), with
  the multiplexer's push replaced by nothing;
- mux: + the multiplexer pairing the samples into frame sets;
- loop: + the frame loop taking each set (Multiplexer.next).

Each stage's cost is the difference with the one before. Both message kinds are run in
the same process: one message per camera-frame (`publish = "cameras"`, the baseline) and
one per node per trigger (`publish = "sets"`).

    python benchmarks/bench_camera_cost.py [--cameras 8 32] [--nodes 4] [--triggers 1200]
                                           [--repeats 3] [--profile]
"""

from __future__ import annotations

import argparse
import cProfile
import os
import pstats
import time
from types import SimpleNamespace

import numpy as np

from calibkit.clitools import print_table
from daemon.capture.multiplexer import Multiplexer
from daemon.nodes.remote import NodeHub
from daemon.publish import zenoh_wire as wire

FPS = 240.0
BLOBS = 12  # per camera-frame: a few bodies' markers and a reflection or two


class _Payload:
    def __init__(self, data: bytes) -> None:
        self.data = data

    def to_bytes(self) -> bytes:
        return self.data


class _Sample:
    """What Zenoh hands a subscriber's callback: a key and a payload."""

    def __init__(self, key: str, data: bytes) -> None:
        self.key_expr, self.payload = key, _Payload(data)


def messages(cameras: int, nodes: int, triggers: int, kind: str, t0_ns: int):
    """Per trigger, the messages the nodes send: (callback name, sample)."""
    rng = np.random.default_rng(1)
    period = 1e9 / FPS
    per_node = np.array_split(np.arange(cameras), nodes)
    out = []
    for k in range(triggers):
        t = t0_ns + round(k * period)
        batch = []
        for n, cams in enumerate(per_node):
            frames = []
            for c in cams:
                uv = rng.uniform(0, 1280, (BLOBS, 2))
                area, peak = rng.uniform(5, 40, BLOBS), rng.uniform(100, 255, BLOBS)
                frames.append((f"cam{c}".encode(), k, t, t + 1_000_000, t, -1, uv, area,
                               peak))
            if kind == "sets":
                batch.append(("_on_sets", _Sample(f"mocap/bench/_nodes/n{n}/blobs",
                                                  wire.encode_sets(n + 1, k, t + 1_100_000,
                                                                   frames))))
            else:
                for f in frames:
                    data = wire.encode_blobs(n + 1, k, f[1], f[2], f[3], t + 1_100_000, f[4],
                                             f[5], f[6], f[7], f[8])
                    batch.append(("_on_blobs", _Sample(f"mocap/bench/{f[0].decode()}/blobs",
                                                       data)))
        out.append(batch)
    return out


def make_hub(cameras: int, nodes: int, push):
    settings = SimpleNamespace(session=SimpleNamespace(rig="bench"), timeout_ms=1e12,
                               max_lag_ms=1e12)
    names = [f"cam{c}" for c in range(cameras)]
    hub = NodeHub(settings, names, {n: n for n in names})
    for n in range(nodes):  # every node's clock known: the daemon's clock, no offset
        node = hub._node(f"n{n}", n + 1)
        for i in range(10):
            node.clock.add(i * 1000, i * 1000 + 10, i * 1000 + 20, i * 1000 + 30)
    caps = hub.sources()
    for cap in caps:
        cap.push, cap.on_open = push, None
        cap.start()
    return hub


def run(batches, cameras: int, nodes: int, kind: str, stage: str) -> float:
    """CPU us per camera-frame of the stages up to `stage`, over the messages `batches`."""
    triggers = len(batches)
    mux = Multiplexer(cameras, fps=FPS)
    hub = make_hub(cameras, nodes, mux.push if stage in ("mux", "loop") else (lambda s: None))
    decode = wire.decode_sets_arrays if kind == "sets" else wire.decode_blobs
    start = time.thread_time_ns()
    for batch in batches:
        for cb, sample in batch:
            if stage == "decode":
                decode(sample.payload.to_bytes())
            else:
                getattr(hub, cb)(sample)
        if stage == "loop":
            while mux.next(0.0) is not None:
                pass
    used = time.thread_time_ns() - start
    if stage in ("mux", "loop"):
        settled = mux.settling
        assert hub.bad == 0, hub.refused
        assert mux.incomplete <= 2 and settled < 30 * cameras, (mux.incomplete, settled)
    return used * 1e-3 / (cameras * triggers)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cameras", type=int, nargs="+", default=[8, 32])
    ap.add_argument("--nodes", type=int, default=4)
    ap.add_argument("--triggers", type=int, default=1200)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--profile", action="store_true",
                    help="also print cProfile's top functions of the full path")
    args = ap.parse_args()
    stages = ("decode", "hub", "mux", "loop")
    rows = []
    for cameras in args.cameras:
        for kind in ("cameras", "sets"):
            batches = messages(cameras, args.nodes, args.triggers, kind, time.monotonic_ns())
            med = {s: float(np.median([run(batches, cameras, args.nodes, kind, s)
                                       for _ in range(args.repeats)])) for s in stages}
            row = [cameras, args.nodes, kind]
            prev = 0.0
            for s in stages:
                row.append(f"{med[s] - prev:.1f}")
                prev = med[s]
            row.append(f"{med['loop']:.1f}")
            row.append(f"{med['loop'] * cameras * FPS * 1e-4:.0f} %")
            rows.append(row)
    print(f"CPU us per camera-frame, median of {args.repeats} runs of {args.triggers} "
          f"triggers ({BLOBS} blobs a camera), load {os.getloadavg()[0]:.1f}")
    print_table(rows, ["cameras", "nodes", "messages", "decode", "hub", "mux", "loop",
                       "total", "of a core at 240 fps"])
    if args.profile:
        for kind in ("cameras", "sets"):
            prof = cProfile.Profile()
            prof.enable()
            cameras = max(args.cameras)
            batches = messages(cameras, args.nodes, args.triggers, kind, time.monotonic_ns())
            run(batches, cameras, args.nodes, kind, "loop")
            prof.disable()
            print(f"\n--- {kind}, {max(args.cameras)} cameras: top functions by own time")
            pstats.Stats(prof).sort_stats("tottime").print_stats(12)


if __name__ == "__main__":
    main()
