"""The control socket's parser for benchmarks/fuzz_parsers.py: one request per input.

Each input goes through what a connection to the socket goes through
(`ControlServer._serve_one`: read up to a newline, JSON, the shape check, the daemon's
`handle`, the answer written back), on a socket pair instead of a listening socket, so
10^5 of them take seconds. The daemon behind it is a stand-in holding what the requests
read (status, a reload that takes at once, no frame yet, the recorder slot); `record` runs
for real in a temporary folder that is the working directory for the run, so a junk path
that happens to be valid starts a recording there and `record_stop` stops it.
"""

from __future__ import annotations

import copy
import json
import os
import socket
import tempfile
import threading
from types import SimpleNamespace

import numpy as np

CMDS = ["status", "stop", "reload", "record", "record_stop", "markers", "", "STATUS", "x"]
VALUES = [None, True, 0, -1, 1.5, float("nan"), 10 ** 40, "", "x", "a.mcap", "b.mcrec",
          "no/such/folder/c.mcap", "d.txt", "e\0.mcap", "é" * 300, [], ["a.mcap"], {},
          {"path": "a.mcap"}]


def _stand_in_daemon():
    """What `daemon.service.control_requests.handle` reads from a daemon, and no more."""
    return SimpleNamespace(
        status=lambda: {"fps": 120.0, "bodies": []},
        stop_event=threading.Event(),
        reloads=SimpleNamespace(ask=lambda: 1, wait=lambda ticket, timeout: (True, None)),
        recorder=None,
        pipeline=SimpleNamespace(last_result=None, hooks=[],
                                 rigid=SimpleNamespace(bodies=[])),
        rig=None, scene=None, config=SimpleNamespace(record_min_free_mb=0.0))


def control():
    """(good inputs, junk(rng), call) for fuzz_parsers.run_parser."""
    from daemon.service import control_requests
    from daemon.service.control import ControlServer

    folder = tempfile.mkdtemp(prefix="fuzz_control_")
    os.chdir(folder)  # where a junk request's valid relative path records
    daemon = _stand_in_daemon()
    server = ControlServer(folder, lambda req: control_requests.handle(daemon, req))
    # the baseline: requests that log nothing (a recording started and stopped logs a line
    # each time, which would count as lines said for bad input); junk starts from all
    good = [json.dumps({"cmd": c}).encode() + b"\n"
            for c in ("status", "reload", "markers", "record_stop")]
    bases = good + [json.dumps({"cmd": "record", "path": "r.mcap"}).encode() + b"\n"]

    def junk(rng) -> bytes:
        pick = lambda seq: copy.deepcopy(seq[int(rng.integers(0, len(seq)))])  # noqa: E731
        kind = rng.random()
        if kind < 0.3:  # random bytes, with or without the newline that ends a request
            data = rng.integers(0, 256, int(rng.integers(0, 200)), np.uint8).tobytes()
            return data + (b"\n" if rng.random() < 0.5 else b"")
        if kind < 0.6:  # a good request with bytes changed or cut
            b = bytearray(pick(bases))
            for _ in range(int(rng.integers(1, 5))):
                b[int(rng.integers(0, len(b)))] = int(rng.integers(0, 256))
            return bytes(b[:int(rng.integers(1, len(b) + 1))])
        # well-formed JSON with any command and values of any type where a path goes
        req = {"cmd": pick(CMDS + VALUES)} if rng.random() < 0.9 else pick(VALUES)
        if isinstance(req, dict):
            for _ in range(int(rng.integers(0, 3))):
                req[pick(["path", "overwrite", "cmd", "x"])] = pick(VALUES)
        return json.dumps(req).encode() + b"\n"

    def call(data: bytes) -> None:
        ours, theirs = socket.socketpair()
        try:
            ours.sendall(data)
            ours.shutdown(socket.SHUT_WR)  # the client has said all it will say
            assert server._slots.acquire(blocking=False)  # as the accept loop takes one
            server._serve_one(theirs)
            answer = json.loads(ours.recv(1 << 20) or b"{}")
            if not isinstance(answer, dict) or "ok" not in answer:
                raise AssertionError(f"no answer to {data[:40]!r}: {answer!r}")
        finally:
            ours.close()
            theirs.close()
            if daemon.recorder is not None and len(daemon.pipeline.hooks) > 1:
                raise AssertionError("two recordings at once")

    return good, junk, call
