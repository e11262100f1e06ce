"""Every parser of a network input and every file reader fed random and corrupted input.

Issue 30's targets: 10^5 fuzzed inputs per parser, no unhandled exception, no server
down, at most one log line per second per kind of bad input. Each parser gets `--inputs`
inputs (random bytes, real messages with bytes changed or cut, random values in the
right places), half of them built from a real message so the parser goes past its first
check. Counted: exceptions that escape the parser's entry point (for file readers:
anything but the one UserError), and the log lines said, per kind: the most lines any
kind got, and that over the run's duration (a run shorter than a second counts as one).

Throughput, junk and the baseline: the same parser on good inputs in the same process,
each the median of `--repeats` batches (inputs per second: what a flood costs the daemon).

The view is a live server in its own process: `--connections` malformed HTTP and websocket
connections, `--concurrency` of them at once (benchmarks/fuzz_view.py), its stderr counted
for lines and tracebacks, then asked for its page and its scene.

    python benchmarks/fuzz_parsers.py [--inputs 100000] [--connections 600] [--repeats 5]
        [--concurrency 128] [--only natnet,mavlink,...,view] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import struct
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path
from types import SimpleNamespace

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from fuzz_control import control  # noqa: E402 - beside this script
from fuzz_view import run_view  # noqa: E402 - beside this script
from fuzz_view_events import EDITS, page_events  # noqa: E402 - beside this script

from calibkit.clitools import print_table, write_json  # noqa: E402
from calibkit.core.errors import UserError  # noqa: E402


class Lines(logging.Handler):
    """Counts the log lines said, by the kind (the text before the first colon after
    'ignoring', or the whole message)."""

    def __init__(self) -> None:
        super().__init__(logging.DEBUG)
        self.kinds: Counter = Counter()
        self.tracebacks = 0

    def emit(self, record: logging.LogRecord) -> None:
        text = record.getMessage()
        kind = text.split("ignoring ", 1)[1].split(":")[0] if "ignoring " in text else text
        self.kinds[kind[:80]] += 1
        self.tracebacks += record.exc_info is not None


def _mutate(rng, data: bytes) -> bytes:
    b = bytearray(data)
    for _ in range(int(rng.integers(0, 5))):
        if b:
            b[int(rng.integers(0, len(b)))] = int(rng.integers(0, 256))
    if rng.random() < 0.5:
        b = b[:int(rng.integers(0, len(b) + 1))]
    return bytes(b)


def _junk(rng, good: list[bytes], max_size: int = 200) -> bytes:
    if rng.random() < 0.5:
        return rng.integers(0, 256, int(rng.integers(0, max_size)), np.uint8).tobytes()
    return _mutate(rng, good[int(rng.integers(0, len(good)))])


# ---- the parsers: each (good inputs, a function making junk, the entry point) ------------

def natnet():
    from daemon.publish import natnet as nn
    from daemon.tracking.rigid import BodyDef

    pub = nn.NatNetPublisher([BodyDef("b", 1, np.eye(3) * 0.05, np.zeros(3))], command_port=0)
    words = [b"Bitstream,4.1", b"FrameRate", b"SubscribeToData,RigidBody,b",
             b"SetRecordTakeName,x", b"StartRecording", b"TimelinePlay", b"Bitstream"]
    good = [struct.pack("<HH", i, 0) for i in (nn.NAT_CONNECT, nn.NAT_REQUEST_MODELDEF,
                                               nn.NAT_KEEPALIVE, nn.NAT_REQUEST_FRAMEOFDATA)]
    good += [struct.pack("<HH", nn.NAT_REQUEST, len(w) + 1) + w + b"\0" for w in words]
    addrs = [("127.0.0.1", 5000), ("10.0.0.9", 5000)]
    k = [0]

    def call(data):
        k[0] += 1
        pub.handle(data, addrs[k[0] % 2])

    return good, lambda rng: _junk(rng, good, 120), call


def mavlink():
    from pymavlink.dialects.v20 import common

    from daemon.publish.mavlink_link import MavlinkLink

    ap = common.MAVLink(None, srcSystem=1, srcComponent=1)
    good = [ap.heartbeat_encode(2, 3, 0, 0, 4).pack(ap), ap.timesync_encode(0, 5).pack(ap),
            ap.timesync_encode(9, 5).pack(ap)]
    link = MavlinkLink("udpout:127.0.0.1:9", 57600, 1, 197)
    link.send = lambda msg: None  # no port: the answers go nowhere
    return good, lambda rng: _junk(rng, good, 64), link.receive


class _FeedSocket:
    """A client's socket for the VRPN server's reader: recv gives the fuzzed bytes once
    (then b"": the client closed), send takes everything."""

    def __init__(self) -> None:
        self.data = b""

    def recv(self, n: int) -> bytes:
        data, self.data = self.data[:n], b""
        return data

    def send(self, data) -> int:
        return len(data)


def vrpn():
    """The VRPN server's two inputs: a UDP datagram asking to be called back ("ADDRESS
    PORT"), and a TCP client's stream (its cookie, then messages: sender and type
    descriptions, a UDP description, pings), handled as the server thread handles them
    (daemon.publish.vrpn.VrpnPublisher._serve_once: an OSError, ValueError or struct.error
    drops that client with one line; anything else would be a bug that escapes)."""
    from daemon.publish import vrpn as vr
    from daemon.publish import vrpn_wire as vw
    from daemon.tracking.rigid import BodyDef

    pub = vr.VrpnPublisher([BodyDef("b", 1, np.eye(3) * 0.05, np.zeros(3))], port=0)
    stream = (vw.describe(vw.SENDER_DESCRIPTION, 0, "b")
              + vw.describe(vw.TYPE_DESCRIPTION, 0, vw.PING) + vw.pack(0, 0)
              + vw.pack(40001, vw.UDP_DESCRIPTION, b"127.0.0.1\0"))
    lobs = [b"127.0.0.1 40000\0", b"10.0.0.9 3883\0"]
    good = lobs + [vw.cookie() + stream, stream]
    feed = _FeedSocket()
    k = [0]

    def call(data):
        k[0] += 1
        if k[0] % 3 == 0:  # a datagram at the UDP port
            if vr._lob_port(data) is None:
                pub._bad_input("a UDP datagram from 127.0.0.1:5000 that is not 'ADDRESS PORT'")
            return
        c = vr._Client(feed, ("127.0.0.1", 40000))
        c.connected = k[0] % 3 == 2  # past the cookie: messages only
        feed.data = data
        try:
            pub._read(c)
        except (OSError, ValueError, struct.error) as exc:
            if not isinstance(exc, ConnectionError):
                pub._bad_input(f"client 127.0.0.1:40000: {exc}")

    return good, lambda rng: _junk(rng, good, 160), call


def zenoh():
    import json as js

    from daemon.nodes.remote import NodeHub
    from daemon.publish import zenoh_wire as wire

    hub = NodeHub(SimpleNamespace(session=SimpleNamespace(rig="lab")), ["cam0"],
                  {"cam0": "cam0"})
    uv = np.array([[1.0, 2.0], [3.0, 4.0]])
    frame = (b"cam0", 1, 100, 110, -1, -1, uv, np.ones(2), np.ones(2))
    msgs = {"blobs": wire.encode_blobs(7, 1, 1, 100, 110, 120, -1, -1, uv, np.ones(2),
                                       np.ones(2)),
            "sets": wire.encode_sets(7, 1, 120, [frame]),
            "pong": wire.encode_pong(7, 1, 10, 20, 30),
            "announce": js.dumps({"node": "n", "boot": 7, "cameras": ["cam0"]}).encode()}
    calls = {"blobs": (hub._on_blobs, "mocap/lab/cam0/blobs"),
             "sets": (hub._on_sets, "mocap/lab/_nodes/n/blobs"),
             "pong": (hub._on_pong, "mocap/lab/_nodes/n/clock"),
             "announce": (hub._on_announce, "mocap/lab/_nodes/n/announce")}
    kinds = sorted(msgs)
    good = [(i, msgs[k]) for i, k in enumerate(kinds)]

    def call(item):
        i, data = item
        fn, key = calls[kinds[i]]
        fn(SimpleNamespace(key_expr=key, payload=SimpleNamespace(to_bytes=lambda: data)))

    def junk(rng):  # each kind's junk to its own callback
        i = int(rng.integers(0, len(kinds)))
        return i, _junk(rng, [msgs[kinds[i]]], 120)

    return good, junk, call


def _file_parser(suffix: str, header: bytes, good_lines: list[bytes], reader):
    folder = Path(tempfile.mkdtemp(prefix="fuzz_parsers_"))
    path = folder / f"input{suffix}"

    def call(data):
        path.write_bytes(header + data)
        try:
            reader(path)
        except UserError:
            pass

    return good_lines, lambda rng: _junk(rng, good_lines, 160), call


def mcrec():
    from calibkit.core.recording import FORMAT, load_observations

    head = json.dumps({"format": FORMAT, "version": 1, "fps": 100.0, "meta": {},
                       "cameras": [{"name": "c0", "size": [640, 480]}]}).encode() + b"\n"
    good = [json.dumps({"f": k, "c": 0, "t": 10 + k, "b": [[1.5, 2.5, 3.0, 9.0]] * (k % 3),
                        "m": [1] * (k % 3)}).encode() + b"\n" for k in range(4)]
    good.append(json.dumps({"truth": 1, "m": [1], "xyz": [[0.1, 0.2, 0.3]]}).encode() + b"\n")
    return _file_parser(".mcrec", head, good, load_observations)


def csv_obs():
    from calibkit.core.recording import load_observations

    head = b"frame,camera,t_ns,u,v,area,peak\n"
    good = [b"1,cam0,1700000000000000000,10.5,20.25,3,200\n" * 3,
            b"2,cam1,1700000000000000001,1,2,3,4\n"]
    return _file_parser(".csv", head, good, load_observations)


def c3d():
    from daemon.formats.c3dio import read_c3d

    data = (ROOT / "fixtures" / "cmu_c3d" / "85_02.c3d").read_bytes()[:6000]
    return _file_parser(".c3d", b"", [data], read_c3d)


def config():
    from daemon.config.mocapd import parse_config

    keys = ["fps", "mode", "interface", "command_port", "rate_hz", "record_from", "address",
            "device", "name", "id", "markers", "cameras", "threshold", "listen", "up_axis"]
    tables = ["pipeline", "tracker", "rigid", "sim", "natnet", "vrpn", "udp", "serial",
              "mavlink", "camera", "replay", "zenoh", "rigid_body"]
    values = [None, True, 0, -1, 7, 1510, 10 ** 30, 1.5, float("nan"), float("inf"), "", "x",
              "auto", "127.0.0.1", "239.255.42.99", [], ["127.0.0.1"], {}, [{}]]
    good = [json.dumps({"natnet": {"record_from": ["127.0.0.1"]}}).encode(),
            json.dumps({"pipeline": {"fps": 120}}).encode()]

    def junk(rng):
        pick = lambda seq: seq[int(rng.integers(0, len(seq)))]  # noqa: E731
        data = {}
        for _ in range(int(rng.integers(1, 4))):
            table = {pick(keys): pick(values) for _ in range(int(rng.integers(0, 4)))}
            data[pick(tables)] = table if rng.random() < 0.8 else pick(values)
        return json.dumps(data).encode()

    def call(data):
        try:
            parse_config(json.loads(data))
        except UserError:
            pass

    return good, junk, call


PARSERS = {"natnet": natnet, "vrpn": vrpn, "mavlink": mavlink, "zenoh": zenoh,
           "mcrec": mcrec, "csv": csv_obs, "c3d": c3d, "config": config,
           "view_events": page_events, "control": control}


def run_parser(name: str, n: int, repeats: int, seed: int) -> dict:
    good, junk, call = PARSERS[name]()
    rng = np.random.default_rng(seed)
    lines = Lines()
    logger = logging.getLogger("mocapd")
    logger.addHandler(lines)
    old_level = logger.level
    logger.setLevel(logging.DEBUG)
    unhandled: Counter = Counter()
    rates = []
    t0 = time.perf_counter()
    per_batch = max(1, n // repeats)
    done = 0
    try:
        while done < n:
            batch = [junk(rng) for _ in range(min(per_batch, n - done))]
            tb = time.perf_counter()
            for data in batch:
                try:
                    call(data)
                except Exception as exc:  # noqa: BLE001 - what the benchmark counts
                    unhandled[type(exc).__name__] += 1
            rates.append(len(batch) / (time.perf_counter() - tb))
            done += len(batch)
        duration = time.perf_counter() - t0
        base = []
        for _ in range(repeats):  # the baseline: good inputs through the same entry point
            batch = [good[i % len(good)] for i in range(min(per_batch, 2000))]
            tb = time.perf_counter()
            for data in batch:
                call(data)
            base.append(len(batch) / (time.perf_counter() - tb))
    finally:
        logger.removeHandler(lines)
        logger.setLevel(old_level)
    most = max(lines.kinds.values(), default=0)
    return {"parser": name, "inputs": done, "unhandled": sum(unhandled.values()),
            "unhandled_kinds": dict(unhandled), "kinds_logged": len(lines.kinds),
            "max_lines_per_kind": most,
            "max_lines_per_kind_per_s": most / max(duration, 1.0),
            "tracebacks": lines.tracebacks, "duration_s": duration,
            "junk_per_s": float(np.median(rates)), "good_per_s": float(np.median(base))}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--inputs", type=int, default=100_000)
    ap.add_argument("--connections", type=int, default=600)
    ap.add_argument("--concurrency", type=int, default=128,
                    help="the view's malformed connections in flight at once")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--seed", type=int, default=30)
    ap.add_argument("--only", default="", help="comma-separated parsers (and 'view')")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    only = [p for p in args.only.split(",") if p] or [*PARSERS, "view"]
    logging.getLogger("mocapd").propagate = False  # counted here, not printed
    results = []
    for name in only:
        r = run_view(args.connections, args.seed, args.concurrency) if name == "view" else \
            run_parser(name, args.inputs, args.repeats, args.seed)
        results.append(r)
        print(f"{name}: done in {r['duration_s']:.1f} s", file=sys.stderr, flush=True)
    print(f"load: {os.getloadavg()[0]:.1f} (1 min average), {os.cpu_count()} cores")
    print_table([[r["parser"], r["inputs"], r["unhandled"], r["tracebacks"], r["kinds_logged"],
                  r["max_lines_per_kind"], round(r["max_lines_per_kind_per_s"], 3),
                  round(r["junk_per_s"]), round(r["good_per_s"])
                  if np.isfinite(r["good_per_s"]) else "-"] for r in results],
                ["parser", "inputs", "unhandled", "tracebacks", "kinds logged",
                 "max lines/kind", "lines/kind/s", "junk inputs/s", "good inputs/s"])
    for r in results:
        if "rss_mb" in r:  # the live view: a leak of sockets or memory would show here
            print(f"view process: RSS {r['rss_mb'][0]:.1f} -> {r['rss_mb'][1]:.1f} MB (peak "
                  f"{r['peak_rss_mb']:.1f}), open fds {r['fds'][0]} -> {r['fds'][1]} (peak "
                  f"{r['peak_fds']}); page served: {r['page']}, scene given: {r['scene']}, "
                  f"same process: {r['same_pid']}")
        if r["parser"] == "view_events":
            r["edits"] = dict(EDITS)
            print("page edits: " + ", ".join(f"{k} {v}" for k, v in sorted(EDITS.items())))
    if args.json:
        write_json(args.json, {"results": results})


if __name__ == "__main__":
    main()
