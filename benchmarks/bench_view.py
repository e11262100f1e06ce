"""The live view's own figures against its targets, with a real browser on the page.

Each run starts `mocapd start --sim --view PORT` (8 cameras at 120 fps, one body) as a
user does, under a notify socket of our own so that READY=1 is timed as systemd sees it,
and opens headless Chromium on the page at READY:

- page up: from READY to the page answering HTTP, and to the browser showing the first
  frame (the page's header names a frame number); beside it, the browser's own cost of
  loading a viser page that holds one line of text (no daemon);
- thumbnails: what the view sends per camera per second (its own count on the page), and
  what the browser takes in (each change of a thumbnail's picture, counted by a mutation
  observer over `--seconds`, per camera);
- 3D view: scene updates the view sends per second (its count on the page), and frames
  the browser draws per second (requestAnimationFrame callbacks over `--seconds`; the
  browser renders WebGL in software here, on the same cores as the daemon).

Targets (the issue): page up within 2 s of READY; thumbnails >= 5 /s per camera for 8
cameras; 3D view >= 30 fps. Medians over `--repeats` runs, each run's figures in a row.

    python benchmarks/bench_view.py [--repeats 3] [--seconds 5] [--json out.json]
"""

from __future__ import annotations

import argparse
import os
import re
import socket
import subprocess
import sys
import tempfile
import threading
import time
import urllib.request
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

from browser import Browser  # noqa: E402  (the tests' DevTools driver)

from calibkit.clitools import print_table, write_json  # noqa: E402


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def one_run(seconds: float) -> dict:
    tmp = Path(tempfile.mkdtemp(prefix="bench-view-"))
    notify = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    notify.bind(str(tmp / "notify"))
    notify.settimeout(0.05)
    port = _free_port()
    env = {**os.environ, "NOTIFY_SOCKET": str(tmp / "notify"), "PYTHONPATH": str(ROOT)}
    (tmp / "m.toml").write_text("[sim]\ncameras = 8\nbodies = 1\nfps = 120.0\n")
    proc = subprocess.Popen([sys.executable, "-m", "daemon.cli", "start", "--config",
                             str(tmp / "m.toml"), "--view", str(port), "--runtime-dir",
                             str(tmp / "rt")], cwd=ROOT, env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    browser = Browser()
    out = {}
    stop = threading.Event()
    try:
        deadline = time.monotonic() + 120
        ready = None
        while ready is None and time.monotonic() < deadline:
            try:
                if b"READY=1" in notify.recv(4096):
                    ready = time.monotonic()
            except TimeoutError:
                if proc.poll() is not None:
                    raise RuntimeError("the daemon ended before READY") from None
        # keep reading the notify socket as systemd does (a full socket blocks the sender)
        def drain():
            while not stop.is_set():
                try:
                    notify.recv(4096)
                except (TimeoutError, OSError):
                    pass

        threading.Thread(target=drain, daemon=True).start()
        browser.open(f"http://127.0.0.1:{port}")
        while True:
            try:
                with urllib.request.urlopen(f"http://127.0.0.1:{port}", timeout=5):
                    out["http_s"] = time.monotonic() - ready
                    break
            except OSError:
                time.sleep(0.02)
        browser.wait_for("document.body && /frame \\d+/.test(document.body.innerText)", 60,
                         poll_s=0.02)
        out["first_frame_s"] = time.monotonic() - ready
        browser.wait_for("[...document.querySelectorAll('img')]"
                         ".filter(i => i.naturalWidth === 240).length === 8", 60)
        time.sleep(2.0)  # the page's own rates are over its last 0.5 s
        changes, raf = browser.js(f"""new Promise(done => {{
            let n = 0, f = 0, on = true;
            const obs = new MutationObserver(records => records.forEach(r => {{
                if (r.type === 'attributes' && r.target.tagName === 'IMG') n++;
                if (r.type === 'childList') r.addedNodes.forEach(a => {{
                    if (a.tagName === 'IMG' || (a.querySelectorAll &&
                        a.querySelectorAll('img').length)) n++; }}); }}));
            obs.observe(document.body, {{subtree: true, childList: true, attributes: true,
                                        attributeFilter: ['src']}});
            const tick = () => {{ if (on) {{ f++; requestAnimationFrame(tick); }} }};
            requestAnimationFrame(tick);
            setTimeout(() => {{ on = false; obs.disconnect(); done([n, f]); }},
                       {int(seconds * 1000)}); }})""")
        text = browser.text()
        m = re.search(r"view: 3D ([0-9.]+)/s, thumbnails ([0-9.]+)/s", text)
        out["scene_sent_hz"] = float(m.group(1)) if m else float("nan")
        out["thumbs_sent_hz"] = float(m.group(2)) if m else float("nan")
        out["thumbs_browser_hz"] = changes / 8 / seconds
        out["browser_fps"] = raf / seconds
        m = re.search(r"(\d+) fps, latency", text)
        out["daemon_fps"] = float(m.group(1)) if m else float("nan")
    finally:
        browser.close()
        proc.terminate()
        proc.wait(30)
        stop.set()
        notify.close()
    return out


def bare_page_s() -> float:
    """The browser's own cost: from opening a viser page that holds one line of text (no
    daemon, no scene) to that text showing. What `first_frame_s` cannot go below."""
    import contextlib
    import io

    import viser

    port = _free_port()
    with contextlib.redirect_stdout(io.StringIO()):
        server = viser.ViserServer(host="127.0.0.1", port=port, verbose=False)
    server.gui.add_markdown("frame 0")
    browser = Browser()
    try:
        t0 = time.monotonic()
        browser.open(f"http://127.0.0.1:{port}")
        browser.wait_for("document.body && document.body.innerText.includes('frame 0')", 60,
                         poll_s=0.02)
        return time.monotonic() - t0
    finally:
        browser.close()
        with contextlib.redirect_stdout(io.StringIO()):
            server.stop()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--seconds", type=float, default=5.0)
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    runs = [one_run(args.seconds) | {"bare_page_s": bare_page_s()}
            for _ in range(args.repeats)]
    keys = [("http_s", "page answers after READY (s)", "<= 2"),
            ("first_frame_s", "browser shows a frame after READY (s)", "<= 2"),
            ("bare_page_s", "  the browser alone: a one-line viser page shows (s)", "-"),
            ("thumbs_sent_hz", "thumbnails sent per camera (/s)", ">= 5"),
            ("thumbs_browser_hz", "thumbnails taken in by the browser per camera (/s)",
             ">= 5"),
            ("scene_sent_hz", "3D updates sent (/s)", ">= 30"),
            ("browser_fps", "3D frames drawn by the browser (/s)", ">= 30"),
            ("daemon_fps", "daemon rate meanwhile (fps)", "120")]
    rows = [[label, target, float(np.median([r[k] for r in runs]))]
            + [r[k] for r in runs] for k, label, target in keys]
    print(f"8 simulated cameras at 120 fps, {args.repeats} runs, {args.seconds:g} s each; "
          f"load average {os.getloadavg()[0]:.1f}")
    print_table(rows, ["figure", "target", "median"] + [f"run {i + 1}"
                                                       for i in range(len(runs))])
    if args.json:
        write_json(args.json, {"runs": runs})


if __name__ == "__main__":
    main()
