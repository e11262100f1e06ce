"""Capture nodes over Zenoh: 32 simulated cameras on 4 nodes at 240 fps into one daemon.

`--cameras N` and `--nodes N` (1-4) run another configuration (the cameras split as
evenly as the nodes allow); `--sweep`, or lists (`--cameras 8,16,32 --nodes 2,4`), run
every configuration, on loopback and in network namespaces, and print one table
(benchmarks/nodes_sweep.py says what each column is).

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

Figures: frame sets complete (sets with all 32 cameras / sets) once every camera is in
and its clock settled (a camera that has just joined is left out of the sets for its
first ~0.1 s, local or remote: that transient is reported apart), tracking against the
simulator's truth (bodies valid, position RMS) beside the local run's; the hop a node adds
(the node got a message's newest frame -> the daemon has the message's frames in its
multiplexer, through the daemon's clock estimate, whose error is the clock figure below;
a frame set cannot be complete before its newest frame, so this is what the node adds to
it; a frame's whole time in its node, waiting for its set's other frames included, is
reported beside it); the clock's offset error and
drift; the killed node's cameras back in the frame sets after its restart, counted from
its first message (and from the process start, which includes building the simulated
scene).

    python benchmarks/bench_nodes.py [--seconds 20] [--cameras 32] [--nodes 4] [--no-link]
                                     [--publish sets|cameras|both] [--json out.json]
    python benchmarks/bench_nodes.py --sweep [--seconds 8] [--where processes|netns|both]
    python benchmarks/bench_nodes.py --cameras 8,16,32 --nodes 2,4 [--seconds 8]
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

sys.path.insert(0, str(Path(__file__).resolve().parent))  # its sibling, when imported
from nodes_figures import (  # noqa: E402
    CLOCKS,
    complete,
    hop_figures,
    never_taken,
    tracking,
    true_offset_ms,
)
from proc_cpu import process_cpu_s as cpu_s  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
ENV = dict(os.environ, PYTHONPATH=str(ROOT))
MAX_NODES = len(CLOCKS)  # each node has a clock of its own
SIM_CAMERAS = (2, 32)  # what a [sim] rig takes (daemon.config.mocapd)


def config_error(cameras: int, nodes: int) -> str | None:
    """Why `cameras` on `nodes` cannot be run (one line), or None."""
    if not SIM_CAMERAS[0] <= cameras <= SIM_CAMERAS[1]:
        return (f"--cameras {cameras}: the simulated rig takes {SIM_CAMERAS[0]} to "
                f"{SIM_CAMERAS[1]} cameras")
    if not 1 <= nodes <= MAX_NODES:
        return f"--nodes {nodes}: the benchmark runs 1 to {MAX_NODES} nodes"
    if cameras < nodes:
        return f"{cameras} cameras cannot go on {nodes} nodes: each node serves at least one"
    return None


def split_cameras(cameras: int, nodes: int) -> list[tuple[int, int]]:
    """Each node's cameras as (first, last) rig indices: as even as can be, the first
    `cameras % nodes` nodes one more; a combination config_error refuses is a bug here."""
    err = config_error(cameras, nodes)
    if err:
        raise ValueError(err)
    per, extra = divmod(cameras, nodes)
    out, first = [], 0
    for k in range(nodes):
        n = per + (k < extra)
        out.append((first, first + n - 1))
        first += n
    return out


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def daemon(conf: Path, seconds: float, out: Path, extra=(), prefix=()):
    """`mocapd start`; `prefix` runs it inside a network namespace (nodes_netns)."""
    return subprocess.Popen([*prefix, sys.executable, "-m", "daemon.cli", "start", "--config",
                             str(conf), "--duration", str(seconds), "--json", str(out),
                             "--realtime", *extra], cwd=ROOT, env=ENV, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)


def node(name, rig, endpoint, cameras, clock, n_cameras=32, seconds=120, publish="sets",
         prefix=()):
    return subprocess.Popen(
        [*prefix, sys.executable, "-m", "daemon.cli", "node", "--sim", "--sim-cameras",
         str(n_cameras),
         "--cameras", cameras, "--name", name, "--rig", rig, "--connect", endpoint,
         "--publish", publish,
         "--clock-offset-ms", str(clock[0]), "--clock-drift-ppm", str(clock[1]),
         "--duration", str(seconds), "--realtime"], cwd=ROOT, env=ENV, stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL)


def status(runtime):
    from daemon.service.control import request

    try:
        return request(runtime, {"cmd": "status"}, timeout_s=2.0)
    except Exception:  # noqa: BLE001 - not up yet, or gone
        return None


def wait_status(runtime, ok, timeout_s, proc=None):
    """The first status that is `ok`, and when; (None, now) after `timeout_s`, or as soon
    as `proc` (the daemon) has ended."""
    end = time.monotonic() + timeout_s
    while time.monotonic() < end and (proc is None or proc.poll() is None):
        st = status(runtime)
        if st is not None and ok(st):
            return st, time.monotonic()
        time.sleep(0.05)
    return None, time.monotonic()


def steady_sets(runtime, seconds: float, pid: int | None = None,
                wait_s: float = 120, n_nodes: int = 0) -> dict | None:
    """Frame sets over `seconds` once every camera is in and settled: from when no sample
    has been left out for its camera's clock settling for a second (a camera that has
    just joined is left out of the sets for its first ~0.1 s, local or remote alike; how
    long all that took is `settle_s`). With the rate reached in that window and the
    status at its end (`end`: its latency figures cover the last 2048 frame sets, its
    nodes' hop the last 4096 messages of each). Before the daemon has opened its cameras
    its status lists them all as connected and has no multiplexer yet: that is waited
    out, and with `n_nodes` that many nodes."""
    t0 = time.monotonic()
    st, _ = wait_status(runtime, lambda s: s.get("multiplexer") is not None
                        and all(c["connected"] for c in s["cameras"])
                        and len(s.get("nodes") or []) >= n_nodes, wait_s)
    if st is None or st.get("multiplexer") is None:
        return None
    last, since = st["multiplexer"]["settling_samples"], time.monotonic()
    while time.monotonic() - since < 1.0:
        time.sleep(0.1)
        st = status(runtime)
        if st is None:
            return None
        if st["multiplexer"]["settling_samples"] != last:
            last, since = st["multiplexer"]["settling_samples"], time.monotonic()
    settled = time.monotonic() - t0 - 1.0
    cpu0 = cpu_s(pid) if pid is not None else None
    st, w0 = status(runtime) or st, time.monotonic()
    time.sleep(seconds)
    st1, w1 = status(runtime), time.monotonic()
    cpu1 = cpu_s(pid) if pid is not None else None
    if st1 is None:
        return None
    # the daemon's CPU time over the camera-frames it took in the window (the window's
    # two status requests are in it too: a few ms in seconds)
    cam_frames = sum(c["frames"] for c in st1["cameras"]) - sum(c["frames"]
                                                                for c in st["cameras"])
    m0, m1 = st["multiplexer"], st1["multiplexer"]
    behind = never_taken(m1) - never_taken(m0)
    made = (st1["frames"] - st["frames"]) + behind
    # the simulator's scorers run in the daemon (on its frame loop, between sets); a rig
    # without --sim has none, so the daemon's own cost is given without them
    scoring = st1.get("scorers_cpu_s", 0.0) - st.get("scorers_cpu_s", 0.0)
    return {"sets": made, "settle_s": settled,
            "complete": complete(m1["incomplete_sets"] - m0["incomplete_sets"], made),
            "late_samples": m1["late_samples"] - m0["late_samples"],
            "skipped_behind": behind,
            "rate_hz": (st1["frames"] - st["frames"]) / (w1 - w0),
            "end": {"latency": st1["latency"], "nodes": st1.get("nodes")},
            "cpu_us_per_camera_frame": (cpu1 - cpu0 - scoring) * 1e6 / cam_frames
            if cpu0 is not None and cpu1 is not None and cam_frames > 0 else float("nan"),
            "scorers_us_per_camera_frame": scoring * 1e6 / cam_frames
            if cam_frames > 0 else float("nan")}


def stop(procs):
    for p in procs:
        if p.poll() is None:
            p.send_signal(signal.SIGTERM)
    for p in procs:
        try:
            p.wait(30)
        except subprocess.TimeoutExpired:
            p.kill()


def sim_toml(path: Path, runtime: Path, rig: str | None, listen, cameras: int):
    """The daemon's mocapd.toml: the [sim] rig, and with `rig` Zenoh on `listen` (a port
    on loopback, or a list of endpoints)."""
    text = f'runtime_dir = "{runtime}"\n[sim]\ncameras = {cameras}\nbodies = 3\n'
    if rig:
        eps = [f"tcp/127.0.0.1:{listen}"] if isinstance(listen, int) else list(listen)
        quoted = ", ".join(f'"{e}"' for e in eps)
        text += f'[zenoh]\nrig = "{rig}"\nlisten = [{quoted}]\ncameras = "announced"\n'
    path.write_text(text)


def run_local(tmp: Path, seconds: float, cameras: int, steady_s: float | None = None) -> dict:
    import json

    conf, out, runtime = tmp / "local.toml", tmp / "local.json", tmp / "run-local"
    sim_toml(conf, runtime, None, None, cameras)
    d = daemon(conf, seconds, out)
    try:
        steady = steady_sets(runtime, steady_s or seconds * 0.3, d.pid)
        d.wait(seconds * 3 + 120)
    finally:
        stop([d])
    res = tracking(json.loads(out.read_text()))
    res["steady"] = steady
    return res


def run_nodes(tmp: Path, seconds: float, cameras: int, publish: str = "cameras",
              n_nodes: int = 4, steady_s: float | None = None) -> dict:
    import json

    port, rig = free_port(), "bench"
    ep = f"tcp/127.0.0.1:{port}"
    conf, out, runtime = tmp / "nodes.toml", tmp / "nodes.json", tmp / "run-nodes"
    sim_toml(conf, runtime, rig, port, cameras)
    d = daemon(conf, seconds, out)
    ranges = [f"{a}-{b}" for a, b in split_cameras(cameras, n_nodes)]
    nodes = [node(f"n{k}", rig, ep, ranges[k], CLOCKS[k], cameras, publish=publish)
             for k in range(n_nodes)]
    procs = [d, *nodes]
    rejoin, before = {}, None
    try:
        st, _ = wait_status(runtime, lambda s: all(c["connected"] for c in s["cameras"])
                            and len(s.get("nodes") or []) == n_nodes, 120)
        if st is None:
            raise SystemExit(f"the {cameras} cameras never all came in")
        before = steady_sets(runtime, steady_s or seconds * 0.3, d.pid)
        k = n_nodes - 1  # the last node is killed and started again
        victim = nodes[k]
        victim.send_signal(signal.SIGKILL)
        victim.wait(10)
        a, b = split_cameras(cameras, n_nodes)[k]
        last = slice(a, b + 1)
        st, _ = wait_status(runtime, lambda s: not any(c["connected"]
                                                       for c in s["cameras"][last]), 5)
        old = {n["boot"] for n in st["nodes"] if n["name"] == f"n{k}"} if st else set()
        started = time.monotonic()
        procs.append(node(f"n{k}", rig, ep, ranges[k], CLOCKS[k], cameras, publish=publish))
        # a daemon that has ended (a short --seconds) is not waited for
        st, first = wait_status(runtime, lambda s: any(n["name"] == f"n{k}"
                                                       and n["boot"] not in old
                                                       for n in s["nodes"]), 120, d)
        st, back = wait_status(runtime, lambda s: all(c["connected"]
                                                      for c in s["cameras"][last]), 30, d)
        rejoin = {"from_first_message_s": back - first if st else None,
                  "from_process_start_s": back - started if st else None}
        d.wait(seconds * 3 + 120)
    finally:
        stop(procs)
    fig = json.loads(out.read_text())
    res = tracking(fig)
    res["rejoin"] = rejoin
    res["steady"] = before
    res["nodes"] = fig["nodes"]
    res.update(hop_figures(fig["nodes"]))
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


def _cell(v) -> str:
    return f"{v:.3f}" if isinstance(v, float) else str(v)


def parse_counts(text: str, option: str) -> list[int]:
    """`8` or `8,16,32` -> [8, 16, 32]; anything else is the user's error (one line)."""
    try:
        out = [int(x) for x in text.split(",")]
    except ValueError:
        out = []
    if not out:
        raise ValueError(f"{option} {text!r}: give a number or numbers joined by commas")
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=None,
                    help="one configuration: the run's length (20); a sweep: each "
                         "configuration's steady window (8)")
    ap.add_argument("--cameras", default=None,
                    help="cameras in all (2-32; default 32), or a list for a sweep (8,16,32)")
    ap.add_argument("--nodes", default=None,
                    help="nodes the cameras are split over (1-4; default 4), or a list (2,4)")
    ap.add_argument("--sweep", action="store_true",
                    help="every configuration (--cameras 8,16,32 --nodes 2,4 unless given), "
                         "one row each, in one table")
    ap.add_argument("--where", choices=("processes", "netns", "both"), default=None,
                    help="a sweep's nodes: on loopback (processes), each in a network "
                         "namespace of its own (netns), or both (the default); implies a sweep")
    ap.add_argument("--no-link", action="store_true", help="skip the delayed-link run")
    ap.add_argument("--steady", type=float, default=None,
                    help="one configuration: the steady window's length (0.3 x --seconds); "
                         "its latency rows cover only the window from 8.6 s (the daemon's "
                         "status keeps the last 2048 frame sets), its hop rows from 17 s "
                         "with sets (a node's last 4096 messages); --seconds must leave "
                         "time after it for the killed node's return")
    ap.add_argument("--publish", choices=("cameras", "sets", "both"), default="sets",
                    help="how the nodes publish: a message per camera frame (cameras), per "
                         "trigger (sets, their default), or both runs one after the other")
    ap.add_argument("--json", type=Path, default=None)
    a = ap.parse_args(argv)
    kinds = ("cameras", "sets") if a.publish == "both" else (a.publish,)
    try:
        cams = parse_counts(a.cameras or ("8,16,32" if a.sweep else "32"), "--cameras")
        nodes = parse_counts(a.nodes or ("2,4" if a.sweep else "4"), "--nodes")
        errs = [e for c in cams for n in nodes if (e := config_error(c, n))]
        if errs:
            raise ValueError(errs[0])
        if a.seconds is not None and not a.seconds > 0:
            raise ValueError(f"--seconds {a.seconds:g}: give a positive length")
        if a.steady is not None and not 0 < a.steady < (a.seconds or 20.0) * 0.8:
            raise ValueError(f"--steady {a.steady:g}: give a positive length under 0.8 x "
                             "--seconds (the rest is start-up and the killed node's return)")
    except ValueError as exc:
        print(f"bench_nodes.py: {exc}", file=sys.stderr)
        raise SystemExit(2) from None
    previous = signal.signal(signal.SIGTERM, _interrupted)
    try:
        if a.sweep or a.where is not None or len(cams) > 1 or len(nodes) > 1:
            from nodes_sweep import sweep  # a sibling script: this folder is on the path

            sweep(cams, nodes, a.where or "both", kinds, a.seconds or 8.0, a.json)
        else:
            single(cams[0], nodes[0], kinds, a.seconds or 20.0, a.no_link, a.json, a.steady)
    except KeyboardInterrupt:
        print("bench_nodes.py: interrupted; the processes and namespaces it started are "
              "stopped and removed", file=sys.stderr)
        raise SystemExit(130) from None
    finally:
        signal.signal(signal.SIGTERM, previous)


def _interrupted(signum, frame):
    """SIGTERM leaves through the same clean-up as Ctrl-C (every `finally` stops what it
    started); a second one while that runs is ignored, so the clean-up is not cut short."""
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    raise KeyboardInterrupt


def steady_rate_skipped(r: dict) -> str:
    """The steady window's frame rate and the sets the frame loop skipped in it."""
    w = r["steady"]
    return "-" if w is None else f"{w['rate_hz']:.1f}, {w['skipped_behind']}"


def steady_latency(r: dict) -> str:
    """Latency to poses from the daemon's status at the steady window's end (its last 2048
    frame sets: inside the window once the window is 8.6 s or more at 240 fps)."""
    lat = None if r["steady"] is None else r["steady"]["end"]["latency"]
    if not lat or lat.get("median_ms") is None:
        return "-"
    return f"{lat['median_ms']:.3f} / {lat['p99_ms']:.3f}"


def steady_hop(r: dict) -> str:
    """The nodes' hop from the status at the steady window's end, against their true
    clocks: median of nodes / worst node's p99 (ms)."""
    nodes = None if r["steady"] is None else r["steady"]["end"].get("nodes")
    h = hop_figures(nodes or [])
    if h.get("hop_true_ms_median") is None:
        return "-"
    return f"{h['hop_true_ms_median']:.3f} / {h['hop_true_ms_p99']:.3f}"


def single(cameras: int, n_nodes: int, kinds, seconds: float, no_link: bool,
           json_path: Path | None, steady_s: float | None = None) -> None:
    """One configuration: local, then through the nodes (one killed and started again),
    then the delayed link; the tables as docs/nodes.md quotes them."""
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        local = run_local(tmp, seconds, cameras, steady_s)
        runs = {}
        for k in kinds:
            (tmp / k).mkdir()
            runs[k] = run_nodes(tmp / k, seconds, cameras, k, n_nodes, steady_s)
        link = None if no_link else run_link(tmp, seconds)
    names = [f"nodes ({k})" for k in kinds]

    def steady(r, key, fmt):
        return "-" if r["steady"] is None else format(r["steady"][key], fmt)

    rows = [["frame sets complete, all cameras in and settled",
             steady(local, "complete", ".4f"),
             *(steady(r, "complete", ".4f") for r in runs.values()), "1"],
            ["  sets in that window, late samples",
             f"{steady(local, 'sets', 'd')}, {steady(local, 'late_samples', 'd')}",
             *(f"{steady(r, 'sets', 'd')}, {steady(r, 'late_samples', 'd')}"
               for r in runs.values()), "-"],
            ["  from all cameras in to settled (s)", steady(local, "settle_s", ".2f"),
             *(steady(r, "settle_s", ".2f") for r in runs.values()), "-"],
            ["  frame rate in that window (fps), sets skipped behind in it",
             *(steady_rate_skipped(r) for r in (local, *runs.values())), "240, 0"],
            ["  latency to poses at its end, median / p99 (ms; the last 2048 sets)",
             *(steady_latency(r) for r in (local, *runs.values())), "p99 <= 3"],
            ["daemon CPU per camera-frame, scorers apart (us; local: with its cameras)",
             steady(local, "cpu_us_per_camera_frame", ".1f"),
             *(steady(r, "cpu_us_per_camera_frame", ".1f") for r in runs.values()), "<= 50"],
            ["  and the simulator's scorers in it, on top (us; no rig has them)",
             steady(local, "scorers_us_per_camera_frame", ".1f"),
             *(steady(r, "scorers_us_per_camera_frame", ".1f") for r in runs.values()),
             "-"]]
    for key in ("frames", "rate_hz", "sets_complete", "skipped_behind", "valid_fraction_min",
                "position_error_mm_rms", "gross_error_frames", "latency_to_poses_ms_median",
                "latency_to_poses_ms_p99"):
        lv = local[key]
        cells = []
        for r in runs.values():
            ratio = r[key] / lv if isinstance(lv, float) and lv else None
            cells.append(_cell(r[key]) + ("" if ratio is None else f" ({ratio:.2f})"))
        rows.append([key + (" (whole run)" if key == "sets_complete" else ""), _cell(lv),
                     *cells, "-"])
    print(f"load {os.getloadavg()[0]:.1f} (1 min), {os.cpu_count()} cores")
    print_table(rows, [f"{cameras} cameras on {n_nodes} nodes, 240 fps", "local",
                       *(f"{n} (/local)" for n in names), "target"])

    def each(fmt):
        return [fmt(r) for r in runs.values()]

    print_table([
        ["hop at the steady window's end, true clocks: median / worst p99 (ms)",
         *each(steady_hop), "p99 <= 1"],
        ["hop node -> daemon, median of nodes (ms)",
         *each(lambda r: f"{r['hop_ms_median']:.3f}"), "<= 0.3"],
        ["hop node -> daemon, worst node's p99 (ms)",
         *each(lambda r: f"{r['hop_ms_p99']:.3f}"), "<= 1"],
        ["  the same against the nodes' true clocks: median / worst p99 (ms)",
         *each(lambda r: "-" if r["hop_true_ms_median"] is None else
               f"{r['hop_true_ms_median']:.3f} / {r['hop_true_ms_p99']:.3f}"), "-"],
        ["  a frame in its node (arrival -> published), median / p99 (ms)",
         *each(lambda r: f"{r['in_node_ms_median']:.3f} / {r['in_node_ms_p99']:.3f}"), "-"],
        ["clock error on loopback, worst node (us)",
         *each(lambda r: f"{r['clock_error_us_loopback_max']:.1f}"), "-"],
        ["killed node's cameras back, from its first message (s)",
         *each(lambda r: f"{r['rejoin'].get('from_first_message_s') or float('nan'):.2f}"),
         "<= 2"],
        ["  ... from its process start (s)",
         *each(lambda r: f"{r['rejoin'].get('from_process_start_s') or float('nan'):.2f}"),
         "-"],
    ], ["figure", *names, "target"])
    if link is not None:
        print_table([
            ["clock error, 1 ms +- 0.2 ms link, median (us)",
             f"{link['offset_error_us_median']:.1f}", "<= 50"],
            ["clock error, 1 ms +- 0.2 ms link, p95 / max (us)",
             f"{link['offset_error_us_p95']:.1f} / {link['offset_error_us_max']:.1f}", "<= 50"],
            ["drift of a 50 ppm node, median / worst error (ppm)",
             f"{link['drift_ppm_median']:.1f} / {link['drift_error_ppm_max']:.1f}",
             "followed"]], ["figure (one node through a delaying relay)", "measured", "target"])
    if json_path:
        write_json(json_path, {"local": local, "nodes": runs, "link": link})


if __name__ == "__main__":
    main()
