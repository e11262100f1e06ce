"""A simulated network link: a TCP relay that delays each direction by a delay and jitter.

Where the kernel has no netem (`tc qdisc ... netem delay 1ms 0.2ms`), tests and
benchmarks put this between a node and the daemon to give the clock estimate a link that
is not loopback. Every chunk read on one side is written to the other `delay_ms` plus a
uniform +-`jitter_ms` after it was read, in order (a chunk never overtakes the one before,
as on one TCP stream); the two directions draw their delays independently, as a link's
two directions do. It listens on one address and connects each accepted connection to
another; only addresses the caller gives (loopback, or its own namespaces).

    python -m daemon.synthetic.link --listen 127.0.0.1:7001 --to 127.0.0.1:7447 \\
        --delay-ms 1 --jitter-ms 0.2 [--seconds 60]
"""

from __future__ import annotations

import argparse
import random
import socket
import threading
import time
from collections import deque

from daemon.capture.sources import fine_timer_slack


def _pump(src: socket.socket, dst: socket.socket, delay_ns: int, jitter_ns: int,
          rng: random.Random) -> None:
    """src -> dst, each chunk held until its due time (never before the previous one's)."""
    queue: deque = deque()
    cond = threading.Condition()
    done = [False]

    def writer():
        fine_timer_slack()
        while True:
            with cond:
                while not queue and not done[0]:
                    cond.wait()
                if not queue:
                    break
                due, data = queue.popleft()
            wait = due - time.monotonic_ns()
            if wait > 0:  # a sleep overruns by tens of us, alike in both directions
                time.sleep(wait * 1e-9)
            try:
                dst.sendall(data)
            except OSError:
                break
        try:
            dst.shutdown(socket.SHUT_WR)
        except OSError:
            pass

    w = threading.Thread(target=writer, daemon=True)
    w.start()
    last = 0
    while True:
        try:
            data = src.recv(65536)
        except OSError:
            data = b""
        now = time.monotonic_ns()
        with cond:
            if not data:
                done[0] = True
                cond.notify()
                break
            last = max(last, now + delay_ns + round(rng.uniform(-jitter_ns, jitter_ns)))
            queue.append((last, data))
            cond.notify()
    w.join()


def serve(listen: tuple[str, int], to: tuple[str, int], delay_ms: float, jitter_ms: float,
          seconds: float | None = None, seed: int = 0) -> None:
    srv = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    srv.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    srv.bind(listen)
    srv.listen(8)
    srv.settimeout(0.5)
    end = None if seconds is None else time.monotonic() + seconds
    rng = random.Random(seed)
    d, j = round(delay_ms * 1e6), round(jitter_ms * 1e6)
    while end is None or time.monotonic() < end:
        try:
            a, _ = srv.accept()
        except TimeoutError:
            continue
        try:
            b = socket.create_connection(to, timeout=2.0)
        except OSError:
            a.close()
            continue
        b.settimeout(None)
        for s in (a, b):
            s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        for x, y in ((a, b), (b, a)):
            threading.Thread(target=_pump, args=(x, y, d, j, random.Random(rng.random())),
                             daemon=True).start()
    srv.close()


def _address(text: str) -> tuple[str, int]:
    host, _, port = text.rpartition(":")
    return host, int(port)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--listen", required=True, type=_address)
    ap.add_argument("--to", required=True, type=_address)
    ap.add_argument("--delay-ms", type=float, default=1.0)
    ap.add_argument("--jitter-ms", type=float, default=0.2)
    ap.add_argument("--seconds", type=float, default=None)
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args(argv)
    serve(a.listen, a.to, a.delay_ms, a.jitter_ms, a.seconds, a.seed)


if __name__ == "__main__":
    main()
