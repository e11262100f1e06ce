"""Capture nodes over Zenoh: 32 simulated cameras on 4 nodes at 240 fps into one daemon.

`--cameras N` spreads N cameras over the 4 nodes instead (the machine's limit shows).

Runs, each a set of separate processes on this machine (loopback only):

- local: `mocapd start --sim --sim-cameras 32` with its cameras in-process (the baseline
  the node runs are compared with, made in the same session);
- nodes: the same [sim] rig, its 32 cameras served by 4 `mocapd node --sim` processes of
  8 cameras each, their clocks offset by seconds and drifting by -50..+50 ppm; one node is
  killed (SIGKILL) mid-run and started again;
- link: one node of 8 cameras reaching the daemon through a relay that delays each
  direction 1 ms +- 0.2 ms (daemon.synthetic.link: this kernel has no netem), its clock
  3.7 s ahead and 50 ppm fast; the daemon's clock estimate is read every half second
  from `mocapd status` and scored against the node's true clock.

Figures: frame sets complete (sets with all 32 cameras / sets), tracking against the
simulator's truth (bodies valid, position RMS) beside the local run's; the hop a node adds
(its frame's arrival there -> the daemon's capture thread has it, through the daemon's
clock estimate, whose error is the clock figure below); the clock's offset error and
drift; the killed node's cameras back in the frame sets after its restart, counted from
its first message (and from the process start, which includes building the simulated
scene).

    python benchmarks/bench_nodes.py [--seconds 20] [--cameras 32] [--no-link] [--json out.json]
"""

from __future__ import annotations

import argparse
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from calibkit.clitools import print_table, write_json

ROOT = Path(__file__).resolve().parents[1]
ENV = dict(os.environ, PYTHONPATH=str(ROOT))
CLOCKS = [(1250.0, 50.0), (-830.0, -50.0), (40.0, 20.0), (3700.0, -10.0)]  # ms, ppm


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def true_offset_ms(offset_ms, drift_ppm, t_ns):
    return (round(t_ns * (1 + drift_ppm * 1e-6)) + round(offset_ms * 1e6) - t_ns) * 1e-6


def daemon(conf: Path, seconds: float, out: Path, extra=()):
    return subprocess.Popen([sys.executable, "-m", "daemon.cli", "start", "--config",
                             str(conf), "--duration", str(seconds), "--json", str(out),
                             *extra], cwd=ROOT, env=ENV, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)


def node(name, rig, endpoint, cameras, clock, n_cameras=32, seconds=120):
    return subprocess.Popen(
        [sys.executable, "-m", "daemon.cli", "node", "--sim", "--sim-cameras", str(n_cameras),
         "--cameras", cameras, "--name", name, "--rig", rig, "--connect", endpoint,
         "--clock-offset-ms", str(clock[0]), "--clock-drift-ppm", str(clock[1]),
         "--duration", str(seconds)], cwd=ROOT, env=ENV, stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL)


def status(runtime):
    from daemon.control import request

    try:
        return request(runtime, {"cmd": "status"}, timeout_s=2.0)
    except Exception:  # noqa: BLE001 - not up yet, or gone
        return None


def wait_status(runtime, ok, timeout_s):
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        st = status(runtime)
        if st is not None and ok(st):
            return st, time.monotonic()
        time.sleep(0.05)
    return None, time.monotonic()


def stop(procs):
    for p in procs:
        if p.poll() is None:
            p.send_signal(signal.SIGTERM)
    for p in procs:
        try:
            p.wait(30)
        except subprocess.TimeoutExpired:
            p.kill()


def tracking(fig) -> dict:
    t = fig.get("truth", {})
    bodies = t.get("bodies", {}).values()
    mux = fig.get("multiplexer") or {}
    n = max(fig["frames"] + (mux.get("skipped_behind") or 0), 1)  # sets made
    return {"frames": fig["frames"], "rate_hz": fig["rate_hz"],
            "sets_complete": 1 - mux.get("incomplete_sets", 0) / n,
            "skipped_behind": mux.get("skipped_behind"),
            "valid_fraction_min": min((b["valid_fraction"] for b in bodies), default=None),
            "position_error_mm_rms": t.get("position_error_mm_rms"),
            "gross_error_frames": t.get("gross_error_frames"),
            "latency_to_poses_ms_median": fig["latency_to_poses"]["median_ms"],
            "latency_to_poses_ms_p99": fig["latency_to_poses"]["p99_ms"]}


def sim_toml(path: Path, runtime: Path, rig: str | None, port: int | None, cameras: int):
    text = f'runtime_dir = "{runtime}"\n[sim]\ncameras = {cameras}\nbodies = 3\n'
    if rig:
        text += (f'[zenoh]\nrig = "{rig}"\nlisten = ["tcp/127.0.0.1:{port}"]\n'
                 'cameras = "announced"\n')
    path.write_text(text)


def run_local(tmp: Path, seconds: float, cameras: int) -> dict:
    conf, out = tmp / "local.toml", tmp / "local.json"
    sim_toml(conf, tmp / "run-local", None, None, cameras)
    daemon(conf, seconds, out).wait()
    import json

    return tracking(json.loads(out.read_text()))


def run_nodes(tmp: Path, seconds: float, cameras: int) -> dict:
    import json

    port, rig = free_port(), "bench"
    ep = f"tcp/127.0.0.1:{port}"
    conf, out, runtime = tmp / "nodes.toml", tmp / "nodes.json", tmp / "run-nodes"
    sim_toml(conf, runtime, rig, port, cameras)
    d = daemon(conf, seconds, out)
    per = cameras // 4
    nodes = [node(f"n{k}", rig, ep, f"{per * k}-{per * k + per - 1}", CLOCKS[k], cameras)
             for k in range(4)]
    procs = [d, *nodes]
    rejoin, before = {}, None
    try:
        st, _ = wait_status(runtime, lambda s: all(c["connected"] for c in s["cameras"])
                            and len(s.get("nodes") or []) == 4, 120)
        if st is None:
            raise SystemExit(f"the {cameras} cameras never all came in")
        t_all = time.monotonic()
        time.sleep(seconds * 0.3)
        st0 = status(runtime)
        before = None
        if st0 is not None and st["multiplexer"] is not None:  # the sets in that span
            m0, m1 = st["multiplexer"], st0["multiplexer"]
            made = (st0["frames"] - st["frames"]) + (m1["skipped_behind"]
                                                     - m0["skipped_behind"])
            before = {"sets": made, "complete": 1 - (m1["incomplete_sets"]
                                                     - m0["incomplete_sets"]) / max(made, 1),
                      "seconds": time.monotonic() - t_all}
        victim = nodes[3]
        victim.send_signal(signal.SIGKILL)
        victim.wait(10)
        last = slice(3 * per, 4 * per)
        st, _ = wait_status(runtime, lambda s: not any(c["connected"]
                                                       for c in s["cameras"][last]), 5)
        old = {n["boot"] for n in st["nodes"] if n["name"] == "n3"} if st else set()
        started = time.monotonic()
        procs.append(node("n3", rig, ep, f"{3 * per}-{4 * per - 1}", CLOCKS[3], cameras))
        st, first = wait_status(runtime, lambda s: any(n["name"] == "n3" and n["boot"] not in old
                                                       for n in s["nodes"]), 120)
        st, back = wait_status(runtime, lambda s: all(c["connected"]
                                                      for c in s["cameras"][last]), 30)
        rejoin = {"from_first_message_s": back - first if st else None,
                  "from_process_start_s": back - started if st else None}
        d.wait(seconds * 3 + 120)
    finally:
        stop(procs)
    fig = json.loads(out.read_text())
    res = tracking(fig)
    res["rejoin"] = rejoin
    res["before_kill"] = before
    res["nodes"] = fig["nodes"]
    errs = []
    for n in fig["nodes"]:
        k = int(n["name"][1:])
        if n["offset_ms"] is not None and n["alive"]:
            errs.append(abs(n["offset_ms"] - true_offset_ms(*CLOCKS[k], n["offset_at_ns"])) * 1e3)
    res["clock_error_us_loopback_max"] = max(errs) if errs else None
    hops = [n for n in fig["nodes"] if n["hop_median_ms"] is not None]
    res["hop_ms_median"] = float(np.median([n["hop_median_ms"] for n in hops]))
    res["hop_ms_p99"] = float(np.max([n["hop_p99_ms"] for n in hops]))
    res["in_node_ms_median"] = float(np.median([n["in_node_median_ms"] for n in hops]))
    res["in_node_ms_p99"] = float(np.max([n["in_node_p99_ms"] for n in hops]))
    return res


def run_link(tmp: Path, seconds: float) -> dict:
    port, link_port, rig = free_port(), free_port(), "benchlink"
    conf, out, runtime = tmp / "link.toml", tmp / "link.json", tmp / "run-link"
    sim_toml(conf, runtime, rig, port, 8)
    d = daemon(conf, seconds + 25, out)
    link = subprocess.Popen([sys.executable, "-m", "daemon.synthetic.link", "--listen",
                             f"127.0.0.1:{link_port}", "--to", f"127.0.0.1:{port}",
                             "--delay-ms", "1", "--jitter-ms", "0.2"], cwd=ROOT, env=ENV)
    clock = (3700.0, 50.0)
    n = node("far", rig, f"tcp/127.0.0.1:{link_port}", "0-7", clock, n_cameras=8)
    errors, drifts, rtts = [], [], []
    try:
        st, t0 = wait_status(runtime, lambda s: (s.get("nodes") or [{}])[0].get("offset_ms")
                             is not None, 120)
        while time.monotonic() < t0 + 20 + seconds and st is not None:
            time.sleep(0.5)
            st = status(runtime)
            if st is None or time.monotonic() < t0 + 20:
                continue  # the estimate's 20 s window filling
            x = st["nodes"][0]
            errors.append((x["offset_ms"] - true_offset_ms(*clock, x["offset_at_ns"])) * 1e3)
            drifts.append(x["drift_ppm"])
            rtts.append(x["rtt_ms"])
    finally:
        stop([d, n, link])
    e = np.abs(errors)
    return {"samples": len(e), "offset_error_us_median": float(np.median(e)),
            "offset_error_us_p95": float(np.percentile(e, 95)),
            "offset_error_us_max": float(e.max()),
            "drift_ppm_median": float(np.median(drifts)),
            "drift_error_ppm_max": float(np.max(np.abs(np.array(drifts) - clock[1]))),
            "rtt_ms_median": float(np.median(rtts))}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--cameras", type=int, default=32, help="in all, on 4 nodes (4-32)")
    ap.add_argument("--no-link", action="store_true", help="skip the delayed-link run")
    ap.add_argument("--json", type=Path, default=None)
    a = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        local = run_local(tmp, a.seconds, a.cameras)
        nodes = run_nodes(tmp, a.seconds, a.cameras)
        link = None if a.no_link else run_link(tmp, a.seconds)
    rows = []
    for key in ("frames", "rate_hz", "sets_complete", "skipped_behind", "valid_fraction_min",
                "position_error_mm_rms", "gross_error_frames", "latency_to_poses_ms_median",
                "latency_to_poses_ms_p99"):
        lv, nv = local[key], nodes[key]
        ratio = nv / lv if isinstance(lv, float) and lv else None
        rows.append([key, lv, nv, "-" if ratio is None else f"{ratio:.2f}"])
    print_table(rows, [f"{a.cameras} cameras, 240 fps", "local", "4 nodes", "nodes/local"])
    link_rows = [] if link is None else [
        ["clock error, 1 ms +- 0.2 ms link, median (us)",
         f"{link['offset_error_us_median']:.1f}", "<= 50"],
        ["clock error, 1 ms +- 0.2 ms link, p95 / max (us)",
         f"{link['offset_error_us_p95']:.1f} / {link['offset_error_us_max']:.1f}", "<= 50"],
        ["drift of a 50 ppm node, median / worst error (ppm)",
         f"{link['drift_ppm_median']:.1f} / {link['drift_error_ppm_max']:.1f}", "followed"]]
    print_table([
        ["hop node -> daemon, median of nodes (ms)", f"{nodes['hop_ms_median']:.3f}", "<= 0.3"],
        ["hop node -> daemon, worst node's p99 (ms)", f"{nodes['hop_ms_p99']:.3f}", "<= 1"],
        ["  of which in the node (arrival -> published), median / p99 (ms)",
         f"{nodes['in_node_ms_median']:.3f} / {nodes['in_node_ms_p99']:.3f}", "-"],
        ["clock error on loopback, worst node (us)", f"{nodes['clock_error_us_loopback_max']:.1f}",
         "-"],
        ["frame sets complete, all nodes up (before the kill)",
         "-" if nodes["before_kill"] is None else f"{nodes['before_kill']['complete']:.3f}",
         "1"],
        *link_rows,
        ["killed node's cameras back, from its first message (s)",
         f"{nodes['rejoin'].get('from_first_message_s') or float('nan'):.2f}", "<= 2"],
        ["  ... from its process start (s)",
         f"{nodes['rejoin'].get('from_process_start_s') or float('nan'):.2f}", "-"],
    ], ["figure", "measured", "target"])
    if a.json:
        write_json(a.json, {"local": local, "nodes": nodes, "link": link})


if __name__ == "__main__":
    main()
