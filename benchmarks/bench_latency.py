"""Latency of the live daemon, frame arrival to UDP datagram: repeated runs, medians.

`mocapd start --sim` in a subprocess, the scene of benchmarks/bench_tracking.py's latency
run (8 cameras at 240 fps, 10 rigid bodies of 5 markers defined live at the start,
triggered multiplexer), sending UDP to this process on 127.0.0.1 for `--seconds`. Two
figures per packet:

- udp: receive time here minus the frame's capture time the packet carries (the daemon's
  estimate from each camera's clock, which includes the camera's smallest transfer delay,
  0.1-0.5 ms in the simulator): what a robot sees;
- daemon: the packet's own latency field, the last sample's arrival to the pose (the
  frame loop alone).

Beside these, the daemon's own stage figures (its `--json` `latency_stages`): capture to
every output handed the result ("sent", the UDP send is inline) and the wait between a set
being complete and the frame loop starting on it ("pickup"), the stage where the tail was.
The daemon runs under real-time scheduling as it does by default; RTPRIO=0 (a variant) runs
it at normal priority, RTPRIO=N at SCHED_RR N. LOAD=N runs N CPU-bound processes beside
the daemon for the run (a machine doing other work; the benchmark's receiver stands in for
a robot on a machine of its own, so it runs at a real-time priority when it may).

Beside the latencies, over the same steady part: the frame rate from the packets' own span
(not the run's nominal length, which holds the daemon's start-up), the frames missing
between the packets' frame numbers (worst run), and the daemon process's CPU time per frame
(all its threads, read from /proc; with --sim that includes the simulated cameras'
rendering) with the cores it keeps busy at that rate: the cost that predicts how a slower
machine will do, where the latencies only say how this one did.

The first second (tracks being found, late cameras opening) is left out. The machine may
be shared: each configuration runs `--repeats` times, alternating, and the table gives
the median of the runs' medians and p99s, and their worst. `--variant NAME=VAR=VALUE,...` adds
a configuration run with extra environment variables; ROOT=PATH runs the daemon of
another checkout (e.g. a `git worktree` of the commit before a change), so a before/after
comparison is made back to back on the same machine. VIEW=1 turns the live web view on
(`--view`), VIEW=browser also keeps a headless Chromium showing it.

    python benchmarks/bench_latency.py [--seconds 10] [--repeats 3] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from calibkit.clitools import print_table, write_json
from daemon.process.realtime import raise_priority, restore_normal
from daemon.publish.packet import decode

sys.path.insert(0, str(Path(__file__).resolve().parent))  # its sibling, when imported
from proc_cpu import process_cpu_s  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
FPS, N_CAMERAS, N_BODIES, PER_BODY, NOISE_PX = 240.0, 8, 10, 5, 0.2
RECEIVER_PRIORITY = 20  # above the daemon's: a robot's receiver is not sharing its cores


def receive_latencies(proc, rx, skip: int) -> dict:
    """Until the daemon `proc` ends: per packet on `rx`, capture to our receipt (ns; one
    monotonic clock on this machine), the daemon's own latency field, the receipt time and
    the frame number; and the daemon's CPU time over the packets after the first `skip`
    (read from /proc every `skip` packets, the last reading before it ended)."""
    lat, daemon_lat, arrival, frames = [], [], [], []
    cpu = []  # (packets so far, the process's CPU s) from packet `skip` on
    while proc.poll() is None:
        try:
            data = rx.recv(65536)
        except TimeoutError:
            continue
        now = time.monotonic_ns()
        p = decode(data)
        lat.append(now - p.t_ns)
        daemon_lat.append(p.latency_ns)
        arrival.append(now)
        frames.append(p.frame)
        if len(lat) >= skip and (len(lat) - skip) % skip == 0:
            c = process_cpu_s(proc.pid)
            if c is not None:
                cpu.append((len(lat), c))
    return {"lat": lat, "daemon_lat": daemon_lat, "arrival": arrival, "frames": frames,
            "cpu": cpu}


def steady_figures(got: dict, skip: int) -> dict:
    """Frame rate, frames missing and the daemon's CPU per frame over the packets after the
    first `skip` (start-up left out): the rate from the packets' own span, not the run's
    nominal length, which holds the daemon's start."""
    arr = np.array(got["arrival"][skip:], dtype=np.int64)
    frames = np.sort(np.array(got["frames"][skip:], dtype=np.int64))
    span_s = (arr[-1] - arr[0]) * 1e-9 if len(arr) > 1 else float("nan")
    missing = int((np.diff(frames) - 1).clip(0).sum()) if len(frames) > 1 else 0
    cpu = got["cpu"]
    per_frame = ((cpu[-1][1] - cpu[0][1]) / (cpu[-1][0] - cpu[0][0]) * 1e3
                 if len(cpu) >= 2 else float("nan"))
    return {"rate_hz": (len(arr) - 1) / span_s, "frames_missing": missing,
            "cpu_ms_per_frame": per_frame}


def open_browser(url: str):
    """Headless Chromium showing the page (its own process group), once the page serves."""
    import shutil
    import tempfile
    import urllib.request

    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        try:
            urllib.request.urlopen(url, timeout=1).close()
            break
        except OSError:
            time.sleep(0.2)
    profile = tempfile.mkdtemp(prefix="chromium-bench-")
    return subprocess.Popen([shutil.which("chromium"), "--headless", "--no-sandbox",
                             "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
                             f"--user-data-dir={profile}", "--remote-debugging-port=0",
                             "--window-size=1400,900", url],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            start_new_session=True, preexec_fn=restore_normal)


def one_run(seconds: float, env: dict, extra: list[str]) -> dict:
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.bind(("127.0.0.1", 0))
    rx.settimeout(0.5)
    port = rx.getsockname()[1]
    cfg = ROOT / "benchmarks" / f".bench_latency_{port}.toml"
    # SCORE=0 (a variant): no truth scoring, the daemon's own cost alone
    score = "false" if env.get("SCORE") == "0" else "true"
    rtprio = int(env.get("RTPRIO", 10))
    figures = cfg.with_suffix(".json")
    cfg.write_text(f"[pipeline]\nrealtime_priority = {rtprio}\n"
                   f"[sim]\nmarkers_per_body = {PER_BODY}\nscore = {score}\n")
    cmd = [sys.executable, "-m", "daemon.cli", "start", "--sim", "--config", str(cfg),
           "--sim-cameras", str(N_CAMERAS), "--sim-bodies", str(N_BODIES),
           "--sim-fps", str(FPS), "--noise-px", str(NOISE_PX),
           "--udp", f"127.0.0.1:{port}", "--duration", str(seconds),
           "--runtime-dir", f"/tmp/mocapd-bench-latency-{port}", "--json", str(figures),
           *extra]
    view = env.get("VIEW")  # VIEW=1: the live web view on; VIEW=browser: and a page open
    browser = None
    if view:
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            view_port = s.getsockname()[1]
        cmd += ["--view", f"127.0.0.1:{view_port}"]
    # LOAD=N: CPU-bound jobs beside the daemon for the run
    load = [subprocess.Popen([sys.executable, "-c", "while True: pass"],
                             preexec_fn=restore_normal) for _ in range(int(env.get("LOAD", 0)))]
    root = env.get("ROOT", str(ROOT))  # another checkout's daemon (its own imports)
    # children start at normal priority, whatever the receiver runs at
    proc = subprocess.Popen(cmd, cwd=root, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            env={**os.environ, "PYTHONPATH": root, **env},
                            preexec_fn=restore_normal)
    if view == "browser":
        browser = open_browser(f"http://127.0.0.1:{view_port}")
    skip = int(FPS)  # the first second: tracks being found, late cameras opening
    try:
        got = receive_latencies(proc, rx, skip)
    finally:
        if browser is not None:
            os.killpg(browser.pid, 15)
            browser.wait(5)
        for job in load:
            job.kill()
            job.wait()
        err = proc.communicate()[1]
        cfg.unlink(missing_ok=True)
        rx.close()
    if proc.returncode != 0:
        raise SystemExit(f"mocapd failed: {err.decode().strip().splitlines()[-1:]}")
    fig = json.loads(figures.read_text())
    figures.unlink()
    stages = fig["latency_stages"]
    if len(got["lat"]) <= 2 * skip:
        raise SystemExit(f"mocapd sent {len(got['lat'])} packets in {seconds:g} s: too few "
                         "to measure (give --seconds 3 or more)")
    a = np.array(got["lat"][skip:]) * 1e-6
    d = np.array(got["daemon_lat"][skip:]) * 1e-6
    return {"packets": len(a), "udp_median_ms": float(np.median(a)),
            "udp_p99_ms": float(np.percentile(a, 99)),
            "daemon_median_ms": float(np.median(d)),
            "daemon_p99_ms": float(np.percentile(d, 99)), **steady_figures(got, skip),
            "sent_median_ms": stages["total"]["median_ms"],
            "sent_p99_ms": stages["total"]["p99_ms"],
            "pickup_p99_ms": stages["pickup"]["p99_ms"], "scheduling": fig["scheduling"]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--variant", action="append", default=[],
                    help="NAME=VAR=VALUE[,VAR=VALUE]: another configuration, run "
                         "alternately with the default one")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    configs = {"default": {}}
    for v in args.variant:
        name, _, rest = v.partition("=")
        configs[name] = dict(kv.split("=", 1) for kv in rest.split(",") if kv)
    # the receiver stands in for a robot on a machine of its own: on this shared machine it
    # must not wait for a core either, or the figure measures its wait, not the daemon's
    print(f"receiver: {raise_priority(RECEIVER_PRIORITY)}", file=sys.stderr)
    runs: dict[str, list[dict]] = {name: [] for name in configs}
    for r in range(args.repeats):
        for name, env in configs.items():
            res = one_run(args.seconds, env, [])
            runs[name].append(res)
            print(f"run {r + 1}/{args.repeats} {name}: udp median {res['udp_median_ms']:.3f} "
                  f"p99 {res['udp_p99_ms']:.3f} ms, {res['packets']} packets, "
                  f"{res['rate_hz']:.1f} fps, {res['cpu_ms_per_frame']:.3f} ms CPU a frame",
                  file=sys.stderr, flush=True)
    rows, out = [], {"seconds": args.seconds, "repeats": args.repeats, "configs": {}}
    for name, rs in runs.items():
        numbers = [k for k in rs[0] if k != "scheduling"]
        med = {k: float(np.median([x[k] for x in rs])) for k in numbers}
        worst = {k: float(np.max([x[k] for x in rs])) for k in numbers}
        out["configs"][name] = {"env": configs[name], "median": med, "worst": worst,
                                "runs": rs}
        rows.append([name, round(med["rate_hz"], 1), int(worst["frames_missing"]),
                     round(med["cpu_ms_per_frame"], 3),
                     round(med["cpu_ms_per_frame"] * med["rate_hz"] / 1e3, 2),
                     round(med["udp_median_ms"], 3),
                     round(med["udp_p99_ms"], 3), round(worst["udp_p99_ms"], 3),
                     round(med["daemon_median_ms"], 3), round(med["daemon_p99_ms"], 3),
                     round(med["sent_median_ms"], 3), round(med["sent_p99_ms"], 3),
                     round(worst["sent_p99_ms"], 3), round(med["pickup_p99_ms"], 3),
                     rs[0]["scheduling"]])
    print_table(rows, ["config", "rate_hz", "missing_worst", "cpu_ms_frame", "cores",
                       "udp_median_ms", "udp_p99_ms",
                       "udp_p99_worst_ms", "daemon_median_ms", "daemon_p99_ms",
                       "sent_median_ms", "sent_p99_ms", "sent_p99_worst_ms", "pickup_p99_ms",
                       "scheduling"])
    if args.json:
        write_json(args.json, out)


if __name__ == "__main__":
    main()
