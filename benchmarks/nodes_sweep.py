"""bench_nodes.py's sweep: every configuration (cameras, nodes, where they run) in one table.

Per camera count, first the local run (the same [sim] rig with its cameras in the daemon's
process: the baseline the tracking accuracy is compared with, made in the same sitting),
then for each node count the cameras split over that many `mocapd node --sim` processes
(as evenly as can be), on loopback ("local processes") and, where the machine can make
them, each node in a network namespace of its own joined to the daemon's by a veth pair
("network namespaces", benchmarks/nodes_netns.py). No node is killed here: the single
configuration's run (`bench_nodes.py --cameras N --nodes N`) measures the rejoin.

A run: the daemon and its nodes start; once every camera is in and its clock has settled,
a steady window of `--seconds`; the daemon's status at the window's end gives the window's
figures; the daemon is then stopped (SIGTERM) for its whole-run tracking figures.

Columns:
- fps: frame sets tracked a second in the window (the cameras run at 240);
- sets complete: sets with every camera / sets made, in the window; skipped: sets the
  frame loop skipped whole because it was behind, in the window;
- hop median / p99: the node got a message's newest frame -> the daemon's multiplexer has
  the message's frames, against the nodes' true clocks (the daemon's clock estimate's
  error at the window's end taken off); the median of the nodes' medians and the worst
  node's p99, over each node's last 4096 messages;
- latency median / p99: a set's newest frame's arrival -> its poses, the last 2048 sets;
- CPU: the daemon process's CPU time over the camera-frames it took in the window, in us
  (the local run's includes its simulated cameras: docs/nodes.md);
- sets skipped behind: also those that fell off the frame loop's full queue (`overflow`);
- bodies valid (worst): the share of frames the least-seen body was posed in, whole run;
- position RMS: the poses against the simulator's truth over the whole run, its ratio
  to the local run of the same camera count, and the frames with a gross error (counted
  in the RMS: a figure counts everything).
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import sys
import tempfile
import time
from pathlib import Path

import bench_nodes as bench
import nodes_netns
from nodes_figures import CLOCKS, hop_figures, tracking

from calibkit.clitools import print_table, write_json

RIG = "sweep"
WAIT_S = 240.0  # a loaded machine took over 90 s to bring a node's cameras up (tests)
WHERE = {"local": "in-process cameras", "processes": "local processes",
         "netns": "network namespaces"}


class RunFailed(RuntimeError):
    """A configuration did not give its figures; the message says what happened."""


def run_one(tmp: Path, cameras: int, nodes: int, where: str, publish: str,
            seconds: float) -> dict:
    """One configuration's figures; `nodes` 0 (where "local") is the in-process run. Every
    process started here is stopped, and every namespace deleted, however this ends."""
    tmp.mkdir(parents=True)
    conf, out, runtime = tmp / "mocapd.toml", tmp / "figures.json", tmp / "run"
    cap_s = seconds * 4 + 600  # the processes end by themselves should this one be killed
    ranges = bench.split_cameras(cameras, nodes) if nodes else []
    spaces = nodes_netns.Namespaces(nodes) if where == "netns" else contextlib.nullcontext()
    try:
        with spaces as ns:
            port = bench.free_port() if nodes and ns is None else None
            listen = ns.listen() if ns is not None else port
            bench.sim_toml(conf, runtime, RIG if nodes else None, listen, cameras)
            procs = []
            try:
                d = bench.daemon(conf, cap_s, out,
                                 prefix=ns.exec(ns.daemon) if ns is not None else ())
                procs.append(d)
                for k, (a, b) in enumerate(ranges):
                    ep = ns.connect(k) if ns is not None else f"tcp/127.0.0.1:{port}"
                    procs.append(bench.node(
                        f"n{k}", RIG, ep, f"{a}-{b}", CLOCKS[k], cameras, seconds=cap_s,
                        publish=publish, prefix=ns.exec(ns.nodes[k]) if ns is not None else ()))
                steady = bench.steady_sets(runtime, seconds, d.pid, WAIT_S, nodes)
                if steady is None:
                    code = d.poll()
                    raise RunFailed(f"the daemon ended early (exit code {code})"
                                    if code is not None else
                                    f"not every camera came in within {WAIT_S:.0f} s")
                d.send_signal(signal.SIGTERM)
                d.wait(WAIT_S)
            finally:
                bench.stop(procs)  # before the namespaces go
    except nodes_netns.NetnsError as exc:
        raise RunFailed(str(exc)) from None
    if not out.exists():
        raise RunFailed("the daemon wrote no figures")
    res = {"steady": steady, "tracking": tracking(json.loads(out.read_text()))}
    if nodes:
        res["hop"] = hop_figures(steady["end"]["nodes"] or [])
    return res


def _row(cfg: dict, res: dict, local: dict | None) -> list:
    """A table row: the configuration, then its figures (or "not run", see the notes)."""
    head = [cfg["cameras"], cfg["nodes"] or "-", WHERE[cfg["where"]], cfg["publish"]]
    if "steady" not in res:
        return head + [f"not run [{res['note']}]"] + ["-"] * 7
    st, tr, hop = res["steady"], res["tracking"], res.get("hop") or {}
    lat = st["end"]["latency"]
    rms = tr["position_error_mm_rms"]
    base = (local or {}).get("tracking", {}).get("position_error_mm_rms")
    ratio = f" ({rms / base:.2f})" if rms is not None and base else ""
    valid = tr["valid_fraction_min"]
    return head + [
        f"{st['rate_hz']:.1f}", f"{st['complete']:.4f}", st["skipped_behind"],
        "-" if hop.get("hop_true_ms_median") is None
        else f"{hop['hop_true_ms_median']:.2f} / {hop['hop_true_ms_p99']:.2f}",
        "-" if lat["median_ms"] is None else f"{lat['median_ms']:.2f} / {lat['p99_ms']:.2f}",
        f"{st['cpu_us_per_camera_frame']:.0f}", "-" if valid is None else f"{valid:.3f}",
        "-" if rms is None else f"{rms:.3f}{ratio}, {tr['gross_error_frames']}"]


HEADER = ["cameras", "nodes", "where", "sent as", "fps", "sets complete", "skipped behind",
          "hop ms, median / p99", "latency ms, median / p99", "CPU us / camera-frame",
          "bodies valid (worst)", "position RMS mm (/ local), gross frames"]


def sweep(cams: list[int], nodes: list[int], where: str, kinds, seconds: float,
          json_path: Path | None) -> None:
    """Every configuration, one row each, and the notes that say why a row was not run."""
    wheres = ("processes", "netns") if where == "both" else (where,)
    why_not = nodes_netns.why_not() if "netns" in wheres else None
    load0, t0 = os.getloadavg(), time.time()
    rows, notes, results = [], [], []

    def note(text: str) -> int:
        if text not in notes:
            notes.append(text)
        return notes.index(text) + 1

    with tempfile.TemporaryDirectory() as tmp:
        for c in cams:
            plan = [(0, "local", "-")] + [(n, w, k) for n in nodes for w in wheres
                                          for k in kinds]
            local = None
            for n, w, k in plan:
                cfg = {"cameras": c, "nodes": n, "where": w, "publish": k}
                if w == "netns" and why_not:
                    res = {"note": note(f"{WHERE[w]}: {why_not}")}
                else:
                    started = time.monotonic()
                    try:
                        res = run_one(Path(tmp) / f"c{c}-n{n}-{w}-{k}", c, n, w, k,
                                      seconds)
                    except RunFailed as exc:
                        res = {"note": note(f"{c} cameras, {n} nodes, {WHERE[w]}: {exc}")}
                    print(f"{time.strftime('%H:%M:%S')} {c} cameras, {n or 'no'} nodes, "
                          f"{WHERE[w]}, {k}: {time.monotonic() - started:.0f} s, load "
                          f"{os.getloadavg()[0]:.1f}", file=sys.stderr)
                if n == 0:
                    local = res if "steady" in res else None
                rows.append(_row(cfg, res, local))
                results.append({**cfg, **res})
    load1 = os.getloadavg()
    print(f"{time.strftime('%Y-%m-%d %H:%M', time.gmtime(t0))} UTC, {os.cpu_count()} cores, "
          f"load average {load0[0]:.1f} / {load0[1]:.1f} / {load0[2]:.1f} (1 / 5 / 15 min) "
          f"at the start, {load1[0]:.1f} / {load1[1]:.1f} / {load1[2]:.1f} at the end; "
          f"steady window {seconds:g} s a configuration, 240 fps, 3 bodies")
    print_table(rows, HEADER)
    for i, text in enumerate(notes, 1):
        print(f"[{i}] {text}")
    if json_path:
        write_json(json_path, {"seconds": seconds, "load_start": load0, "load_end": load1,
                               "runs": results})
