"""What a reload's swap costs the frame loop, in CPU time: the swap, the first frame after
it and the two after that, against the frames with no reload near, in the same run.

Why: bench_reload.py measures what a client sees (each datagram's delay), which on a
shared machine also holds every other process's and thread's doing. This one runs the
daemon in this process (`--sim`, live, on a thread) and times the swap
(`Pipeline._apply_pending`) and each frame (`Pipeline.process`) in the frame loop thread's
own CPU time (`time.thread_time_ns`), which another process's load does not inflate: the
swap's own cost, apart from the machine's. Reloads rotate as in bench_reload.py: a rigid
body removed and added back, a second UDP output added and removed, a `[tracker]` gate
changed.

    python benchmarks/bench_reload_swap.py [--reloads 20] [--every-s 0.7] [--fps 120]
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import threading
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from calibkit.clitools import print_table  # noqa: E402

KINDS = ("body removed", "body added", "output added", "output removed", "new tracker")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--reloads", type=int, default=20)
    ap.add_argument("--every-s", type=float, default=0.7)
    ap.add_argument("--fps", type=float, default=120.0)
    args = ap.parse_args()
    from daemon.config.mocapd import load_config
    from daemon.service.daemon import Daemon

    load0 = os.getloadavg()[0]
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        cfg, rt = folder / "mocapd.toml", folder / "rt"
        head = f"[sim]\nfps = {args.fps}\n\n[[udp]]\naddress = \"127.0.0.1:9\"\n"
        cfg.write_text(head)
        daemon = Daemon(replace(load_config(cfg), runtime_dir=rt),
                        extend=lambda c: replace(c, runtime_dir=rt))
        thread = threading.Thread(target=daemon.run, daemon=True,
                                  kwargs={"duration_s": args.reloads * args.every_s + 60})
        thread.start()
        deadline = time.monotonic() + 300
        while getattr(daemon, "pipeline", None) is None or daemon.pipeline.stats.frames < 480:
            if time.monotonic() > deadline or not thread.is_alive():
                raise SystemExit("bench_reload_swap: the daemon did not start tracking")
            time.sleep(0.05)
        learned = rt / "sim-bodies.toml"
        bodies = learned.read_text() if learned.exists() else ""
        cut = bodies.rfind("[[rigid_body]]")
        fewer = bodies[:cut] if cut > 0 else bodies
        pipeline = daemon.pipeline
        frames: list[tuple[str | None, float]] = []  # (swapped just before, CPU ms)
        swaps: list[float] = []  # each swap's own CPU ms (Pipeline._apply_pending)
        swapping: list[str] = []
        swapped: list[str] = []
        process, apply = pipeline.process, pipeline._apply_pending

        def timed_swap():
            t0 = time.thread_time_ns()
            apply()
            swaps.append((time.thread_time_ns() - t0) * 1e-6)
            if swapping:
                swapped[:] = [swapping.pop()]

        def timed(fs):
            t0 = time.thread_time_ns()
            result = process(fs)  # swaps first when one is waiting (timed_swap)
            ms = (time.thread_time_ns() - t0) * 1e-6
            frames.append((swapped.pop() if swapped else None, ms))
            return result

        pipeline._apply_pending, pipeline.process = timed_swap, timed
        state = {"bodies": bodies, "extra": "", "gate": ""}
        for k in range(args.reloads):
            time.sleep(args.every_s)
            kind = KINDS[k % len(KINDS)]
            if kind.startswith("body"):
                state["bodies"] = fewer if kind == "body removed" else bodies
            elif kind.startswith("output"):
                state["extra"] = ("[[udp]]\naddress = \"127.0.0.1:10\"\n"
                                  if kind == "output added" else "")
            else:
                state["gate"] = "" if state["gate"] else "[tracker]\ngate_px = 3.5\n"
            cfg.write_text(head + state["extra"] + state["gate"] + "\n" + state["bodies"])
            swapping[:] = [kind]
            if not daemon.reload():
                raise SystemExit(f"bench_reload_swap: reload {k + 1} ({kind}) failed: "
                                 f"{daemon.reload_error}")
            print(f"reload {k + 1}/{args.reloads}: {kind}", file=sys.stderr)
        time.sleep(args.every_s)
        pipeline.process, pipeline._apply_pending = process, apply
        daemon.stop_event.set()
        thread.join(60)
    cpu = np.array([ms for _k, ms in frames])
    after_swap = [i for i, (k, _ms) in enumerate(frames) if k is not None]
    near = np.zeros(len(frames), bool)
    for i in after_swap:
        near[max(i - 1, 0):i + 3] = True
    base = cpu[~near]
    table = []
    for kind in KINDS:
        at = [i for i in after_swap if frames[i][0] == kind]
        if at:
            first = cpu[at]
            later = np.concatenate([cpu[i + 1:i + 3] for i in at])
            table.append([kind, len(at), f"{np.median(first):.2f}", f"{first.max():.2f}",
                          f"{np.median(later):.2f}", f"{later.max():.2f}"])
    table.append(["no reload near", len(base), f"{np.median(base):.2f}",
                  f"{np.percentile(base, 99):.2f} (p99)", "", ""])
    print_table(table, ["the first frame after a swap", "n", "CPU ms, median", "worst",
                        "2 frames after: median", "worst"])
    print(f"the swaps themselves: {len(swaps)}, CPU median {np.median(swaps):.2f} ms, worst "
          f"{max(swaps):.2f} ms (in the frame loop, between frames or at a frame's start)")
    print(f"frame period {1e3 / args.fps:.2f} ms; the frame loop thread's CPU time per "
          f"frame; load average {load0:.1f} -> {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
