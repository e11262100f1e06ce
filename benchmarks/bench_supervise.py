"""How long the supervised parts outside the daemon's loops take to come back (issue 30).

One `mocapd start --sim` daemon in this process, with the live view (`--view` on a free
loopback port) and a [zenoh] table (a free loopback endpoint). Each repeat:
- kills the view process with SIGKILL and times until a new one serves the page (HTTP 200)
  and has taken a frame from the feed;
- closes the Zenoh session under the daemon and times until the hub has a new open one.
Between repeats the daemon runs a second. The back-off is what a part that keeps failing
gets; here each repeat must time one restart, so every run counts as healthy
(supervise.HEALTHY_S = 0): the wait before each restart is the base 0.2 s.
Baseline in the same process: the first view process's start (ViewLink made -> page
served), which a restart repeats, and the first session's open.

    python benchmarks/bench_supervise.py [--runs 5] [--json out.json]
"""

from __future__ import annotations

import argparse
import os
import signal
import socket
import tempfile
import threading
import time
import urllib.request
from dataclasses import replace
from pathlib import Path

import numpy as np

from calibkit.clitools import print_table, write_json

SIM = "[sim]\ncameras = 4\nbodies = 2\nfps = 60.0\nseed = 3\n"
DEADLINE_S = 120.0
OPENER = urllib.request.build_opener(urllib.request.ProxyHandler({}))


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _serves(port: int) -> bool:
    try:
        with OPENER.open(f"http://127.0.0.1:{port}/", timeout=5) as r:
            return r.status == 200
    except OSError:
        return False


def _until(cond) -> float:
    t0 = time.monotonic()
    while not cond():
        if time.monotonic() - t0 > DEADLINE_S:
            raise SystemExit("timed out")
        time.sleep(0.01)
    return time.monotonic() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--json")
    args = ap.parse_args()

    import daemon.process.supervise as supervise
    from daemon.config.mocapd import load_config
    from daemon.service.daemon import Daemon
    from daemon.view.link import ViewLink

    supervise.HEALTHY_S = 0.0
    tmp = Path(tempfile.mkdtemp(prefix="bench_supervise_"))
    port = _free_port()
    cfg_path = tmp / "mocapd.toml"
    cfg_path.write_text(SIM + f'[zenoh]\nrig = "b"\nlisten = ["tcp/127.0.0.1:{_free_port()}"]\n')
    rt = tmp / "rt"
    d = Daemon(replace(load_config(cfg_path), runtime_dir=rt),
               extend=lambda c: replace(c, runtime_dir=rt))
    t0 = time.monotonic()
    d.view = ViewLink("127.0.0.1", port)
    _until(lambda: _serves(port))
    first_view = time.monotonic() - t0
    th = threading.Thread(target=d.run, kwargs={"duration_s": 3600.0}, daemon=True)
    th.start()
    _until(lambda: getattr(d, "pipeline", None) is not None and d.pipeline.stats.frames > 30)
    view_s, zenoh_s = [], []
    try:
        for _ in range(args.runs):
            time.sleep(1.0)
            n, sent = d.view.restarts, d.view.sent
            kill_t = time.monotonic()
            os.kill(d.view.process.pid, signal.SIGKILL)
            _until(lambda n=n, sent=sent: d.view.restarts > n and d.view.sent > sent
                   and _serves(port))
            view_s.append(time.monotonic() - kill_t)
            time.sleep(1.0)
            old = d.hub.session
            close_t = time.monotonic()
            old.close()
            _until(lambda old=old: d.hub.session is not old
                   and not d.hub.session.is_closed())
            zenoh_s.append(time.monotonic() - close_t)
        t1 = time.monotonic()
        # the same settings on another free port (the daemon's is its session's)
        other = replace(d.hub.settings.session, listen=(f"tcp/127.0.0.1:{_free_port()}",))
        other.open().close()
        open_s = time.monotonic() - t1
    finally:
        d.handle({"cmd": "stop"})
        th.join(30)
    load = os.getloadavg()
    fig = {"runs": args.runs, "view_restart_s": view_s, "zenoh_reopen_s": zenoh_s,
           "view_first_start_s": first_view, "zenoh_open_s": open_s,
           "load": [round(x, 2) for x in load]}
    print_table([["view: SIGKILL -> new process serving and fed, median (s)",
                  float(np.median(view_s))],
                 ["view: same, worst (s)", max(view_s)],
                 ["baseline: the first view process started -> serving (s)", first_view],
                 ["zenoh: session closed -> reopened, median (s)", float(np.median(zenoh_s))],
                 ["zenoh: same, worst (s)", max(zenoh_s)],
                 ["baseline: a session opened and closed (s)", open_s]],
                ["figure", "value"])
    print(f"load average {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}, {args.runs} runs")
    if args.json:
        write_json(args.json, fig)


if __name__ == "__main__":
    main()
