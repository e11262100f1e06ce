"""Zenoh's one-way latency on this machine, and what co-located capture work does to it.

Why: the node -> daemon hop (bench_nodes.py) is Zenoh's transport plus whatever holds the
cores when a set is ready. This measures the transport alone, between processes on
loopback at 240 messages a second of a set's size, then with 4 publishers that each do
about as much CPU work per trigger as a simulated node (all woken at the same instant,
as a hardware trigger does), under SCHED_RR: with the publishers' Zenoh threads at their
work's priority, and one step above it (daemon.nodes.node.Node.start does the latter).

    python benchmarks/zenoh_floor.py [--seconds 8] [--repeats 3] [--work-ms 0.55]

Needs root (or CAP_SYS_NICE) for the real-time rows; without it they say so. Prints the
median over repeats of each row's median / p90 / p99, and each row's p99 against the
first row's (the transport alone), measured in the same run.
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import struct
import subprocess
import sys
import time

import numpy as np

RATE_HZ = 240.0
SIZE = 5000  # bytes: 8 cameras' blobs, about what a node's set carries


def _config(endpoint: str, listen: bool):
    import zenoh

    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("scouting/gossip/enabled", "false")
    conf.insert_json5("listen/endpoints" if listen else "connect/endpoints",
                      json.dumps([endpoint]))
    return conf


def _rr(priority: int) -> None:
    if priority > 0:
        os.sched_setscheduler(0, os.SCHED_RR, os.sched_param(priority))


def run_subscriber(endpoint: str, seconds: float, priority: int) -> None:
    import zenoh

    sys.setswitchinterval(1e-4)
    _rr(priority)
    session = zenoh.open(_config(endpoint, listen=True))
    lat: list[int] = []

    def got(sample) -> None:
        now = time.monotonic_ns()
        lat.append(now - struct.unpack_from("<q", sample.payload.to_bytes())[0])

    sub = session.declare_subscriber("floor/x", got)
    time.sleep(seconds + 3.0)
    sub.undeclare()
    session.close()
    keep = np.asarray(lat[len(lat) // 5:], dtype=np.float64) * 1e-6  # past the start
    print(json.dumps({"n": len(keep), "median": float(np.median(keep)),
                      "p90": float(np.percentile(keep, 90)),
                      "p99": float(np.percentile(keep, 99))}))


def run_publisher(endpoint: str, seconds: float, t0: float, work_ms: float,
                  priority: int, network_priority: int) -> None:
    import zenoh

    sys.setswitchinterval(1e-4)
    _rr(network_priority)  # Zenoh's threads start with the session: they inherit this
    session = zenoh.open(_config(endpoint, listen=False))
    _rr(priority)  # the work (and the put) at the capture threads' priority
    pub = session.declare_publisher("floor/x", express=True,
                                    congestion_control=zenoh.CongestionControl.DROP,
                                    priority=zenoh.Priority.INTERACTIVE_HIGH)
    pad = bytes(SIZE - 8)
    x = np.random.default_rng(0).random((8, 300, 3))
    unit = _unit_ms(x)
    units = round(work_ms / unit) if work_ms > 0 else 0
    for k in range(int(seconds * RATE_HZ)):
        due = t0 + k / RATE_HZ
        while (left := due - time.monotonic()) > 0:
            time.sleep(left)
        for _ in range(units):  # a node's detection of its cameras' frames
            np.sin(x).sum()
        pub.put(struct.pack("<q", time.monotonic_ns()) + pad)
    time.sleep(0.5)
    session.close()


def _unit_ms(x) -> float:
    t = time.perf_counter()
    for _ in range(50):
        np.sin(x).sum()
    return (time.perf_counter() - t) / 50 * 1e3


def one(seconds: float, publishers: int, work_ms: float, rt: bool, step: int) -> dict:
    """One row's run: a subscriber (the daemon) and `publishers` nodes."""
    from soak import free_port  # benchmarks/soak.py, beside this script

    endpoint = f"tcp/127.0.0.1:{free_port(socket.SOCK_STREAM)}"
    me = [sys.executable, __file__]
    prio = 10 if rt else 0
    sub = subprocess.Popen([*me, "--role", "sub", "--endpoint", endpoint, "--seconds",
                            str(seconds), "--priority", str(prio)], stdout=subprocess.PIPE,
                           text=True)
    time.sleep(1.0)
    t0 = time.monotonic() + 2.0
    pubs = [subprocess.Popen([*me, "--role", "pub", "--endpoint", endpoint, "--seconds",
                              str(seconds), "--t0", repr(t0), "--work-ms", str(work_ms),
                              "--priority", str(prio - 1 if rt else 0),
                              "--network-priority", str(prio - 1 + step if rt else 0)])
            for _ in range(publishers)]
    for p in pubs:
        p.wait()
    out, _ = sub.communicate()
    return json.loads(out.strip().splitlines()[-1])


ROWS = (  # label, publishers, with work, real-time, network step above the work
    ("1 publisher, no work", 1, False, False, 0),
    ("4 publishers, no work", 4, False, False, 0),
    ("4 publishers, work, SCHED_RR, network level with work", 4, True, True, 0),
    ("4 publishers, work, SCHED_RR, network a step above", 4, True, True, 1),
)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=8.0)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--work-ms", type=float, default=0.55,
                    help="CPU work per trigger per publisher (ms; a simulated node's 8 "
                         "cameras take about 0.4)")
    ap.add_argument("--role", choices=("sub", "pub"), help=argparse.SUPPRESS)
    ap.add_argument("--endpoint", help=argparse.SUPPRESS)
    ap.add_argument("--t0", type=float, help=argparse.SUPPRESS)
    ap.add_argument("--priority", type=int, default=0, help=argparse.SUPPRESS)
    ap.add_argument("--network-priority", type=int, default=0, help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.role == "sub":
        return run_subscriber(a.endpoint, a.seconds, a.priority)
    if a.role == "pub":
        return run_publisher(a.endpoint, a.seconds, a.t0, a.work_ms, a.priority,
                             a.network_priority)
    if a.seconds <= 0 or a.repeats < 1 or a.work_ms < 0:
        sys.exit("zenoh_floor: --seconds and --repeats must be positive, --work-ms >= 0")
    rt_ok = os.geteuid() == 0
    from calibkit.clitools import print_table

    rows, base = [], None
    for label, n, work, rt, step in ROWS:
        if rt and not rt_ok:
            rows.append([label, "-", "-", "-", "needs root or CAP_SYS_NICE"])
            continue
        runs = []
        for r in range(a.repeats):
            print(f"{label}: run {r + 1} of {a.repeats}", file=sys.stderr, flush=True)
            runs.append(one(a.seconds, n, a.work_ms if work else 0.0, rt, step))
        med = {k: float(np.median([x[k] for x in runs])) for k in ("median", "p90", "p99")}
        base = base if base is not None else med["p99"]
        rows.append([label, f"{med['median']:.3f}", f"{med['p90']:.3f}", f"{med['p99']:.3f}",
                     f"{med['p99'] / base:.2f}"])
    print(f"{time.strftime('%Y-%m-%d %H:%M', time.gmtime())} UTC, {os.cpu_count()} cores, "
          f"load {os.getloadavg()[0]:.1f}, {RATE_HZ:.0f} messages/s per publisher of "
          f"{SIZE} bytes, work {a.work_ms} ms a trigger, median of {a.repeats} runs")
    print_table(rows, ["configuration", "median ms", "p90 ms", "p99 ms", "p99 / row 1"])


if __name__ == "__main__":
    main()
