"""The live view's web server fuzzed with many malformed connections at once (issue 30).

Why a module of its own: a connection is much slower than a datagram, and one at a time
(a junk request can leave the server waiting for the rest) 10^5 of them took hours. Here
an asyncio client keeps `concurrency` connections in flight, each one kind of junk:
random bytes, broken request lines, oversized headers, websocket handshakes with the
view's protocol and an old one followed by junk frames, a good handshake closed with no
frame, and a request cut half way and left open until the server's own timeout closes it
(those few in a pool of their own, `held`, so they do not starve the rest). The view
process's stderr is counted for lines per kind and tracebacks; at the end the page must
still be served, a websocket client with the view's protocol must still get the scene
(viser's first message batch, with the page's heading), and the process must be the same
one; its RSS and open file descriptors are read before and after (a leaked socket shows).
"""

from __future__ import annotations

import asyncio
import base64
import os
import tempfile
import time
from collections import Counter

import numpy as np

from tests.test_fuzz_view import _frame as ws_frame  # the tests' frames (ROOT on the path)

KINDS = ("random bytes", "broken request line", "oversized headers", "handshake + junk",
         "old protocol + junk", "handshake, no frame", "request cut, left open")
HELD_EVERY = 50  # one connection in 50 is a cut request left open
WAIT_S = 0.3  # how long junk that may decode into something harmless waits for an answer
DEADLINE_S = 30.0  # any one connection, whatever the server does (the server's is 10 s)


def proc_usage(pid: int) -> tuple[float, int]:
    """(RSS in MB, open file descriptors) of a process, from /proc."""
    with open(f"/proc/{pid}/status") as f:
        rss_kb = next(int(ln.split()[1]) for ln in f if ln.startswith("VmRSS:"))
    return rss_kb / 1024.0, len(os.listdir(f"/proc/{pid}/fd"))


def handshake(protocol: str | None) -> bytes:
    key = base64.b64encode(os.urandom(16)).decode()
    proto = f"Sec-WebSocket-Protocol: {protocol}\r\n" if protocol else ""
    return (f"GET / HTTP/1.1\r\nHost: x\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
            f"Sec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n{proto}\r\n").encode()


async def _read_reply(reader: asyncio.StreamReader) -> bytes:
    """The reply's head (up to its blank line), or what came before the server closed."""
    try:
        return await reader.readuntil(b"\r\n\r\n")
    except asyncio.IncompleteReadError as exc:
        return exc.partial
    except asyncio.LimitOverrunError:
        return await reader.read(65536)


async def read_frame(reader: asyncio.StreamReader) -> tuple[int, bytes]:
    """One frame from the server (unmasked): (opcode, payload)."""
    b0, b1 = await reader.readexactly(2)
    n = b1 & 0x7F
    if n == 126:
        n = int.from_bytes(await reader.readexactly(2), "big")
    elif n == 127:
        n = int.from_bytes(await reader.readexactly(8), "big")
    return b0 & 15, await reader.readexactly(n)


def viser_messages(payload: bytes) -> list[dict]:
    """A viser message batch as its server sends it: the msgpack part's sizes, then
    zstd-compressed msgpack ({"messages": [...]}), then binary buffers."""
    # deferred on purpose: viser's own wire libraries, only where used
    import msgspec
    import zstandard

    size = int.from_bytes(payload[:8], "little")
    comp = int.from_bytes(payload[8:16], "little")
    inner = zstandard.ZstdDecompressor().decompress(payload[16:16 + comp], max_output_size=size)
    return list(msgspec.msgpack.decode(inner)["messages"])


def _junk_request(rng, kind: int) -> bytes:
    if kind == 0:
        return rng.integers(0, 256, int(rng.integers(1, 300)), np.uint8).tobytes()
    if kind == 1:
        words = [b"GET", b"POST", b"GARBAGE", b"G\x00T", b""]
        path = rng.integers(33, 127, int(rng.integers(0, 60)), np.uint8).tobytes()
        version = [b"HTTP/1.1", b"HTTP/9.9", b"HTTP/1", b"", b"\xff\xfe"]
        extra = [b"", b"Upgrade: websocket\r\n", b"Content-Length: -1\r\n",
                 b"Transfer-Encoding: chunked\r\n", b"Host x\r\n"]
        return (words[int(rng.integers(0, 5))] + b" /" + path + b" "
                + version[int(rng.integers(0, 5))] + b"\r\n" + extra[int(rng.integers(0, 5))]
                + b"\r\n")
    # oversized: a long path, many headers, one long header
    pick = int(rng.integers(0, 3))
    if pick == 0:
        return b"GET /" + b"a" * int(rng.integers(8000, 70000)) + b" HTTP/1.1\r\n\r\n"
    if pick == 1:
        return b"GET / HTTP/1.1\r\nHost: x\r\n" + b"X: y\r\n" * int(rng.integers(120, 2000)) \
            + b"\r\n"
    return b"GET / HTTP/1.1\r\nHost: x\r\nX: " + b"y" * int(rng.integers(8000, 70000)) \
        + b"\r\n\r\n"


def _junk_frames(rng) -> bytes:
    out = b""
    for _ in range(int(rng.integers(1, 4))):
        payload = rng.integers(0, 256, int(rng.integers(0, 200)), np.uint8).tobytes()
        opcode = int(rng.choice([1, 2, 2, 2, 0, 8, 9, 10, 3, 11]))
        out += ws_frame(payload, opcode, mask=rng.random() < 0.9,
                        rsv=int(rng.integers(0, 8)) if rng.random() < 0.1 else 0,
                        fin=rng.random() < 0.9)
    if rng.random() < 0.1:  # a frame claiming more than it holds, or more than 50 MB
        out += bytes([0x82, 0xFF]) + int(rng.integers(1 << 20, 1 << 62)).to_bytes(8, "big")
    return out


async def _until_closed(reader, writer, wait_s: float) -> None:
    try:
        while await asyncio.wait_for(reader.read(65536), wait_s):
            pass
    except (asyncio.TimeoutError, OSError):
        pass


async def _one(port: int, kind: int, rng, protocol: str, outcome: Counter) -> None:
    """One malformed connection of a kind; how it ended goes in `outcome`."""
    t0 = time.monotonic()
    reader, writer = await asyncio.open_connection("127.0.0.1", port, limit=1 << 20)
    try:
        if kind <= 2:
            writer.write(_junk_request(rng, kind))
            await writer.drain()
            if kind == 0:
                writer.write_eof()  # a client that hangs up after its bytes
            await _until_closed(reader, writer, 15.0)
        elif kind in (3, 4, 5):
            writer.write(handshake(protocol if kind != 4 else "viser-v0.0.1"))
            reply = await asyncio.wait_for(_read_reply(reader), 15.0)
            outcome[f"{KINDS[kind]}: {reply.split(b' ', 2)[1:2]}"] += 1
            if kind == 5:
                if rng.random() < 0.5:  # an abrupt end: a reset, not a close
                    writer.transport.abort()
                return
            writer.write(_junk_frames(rng))
            await writer.drain()
            await _until_closed(reader, writer, WAIT_S)
        else:  # cut half way, left open: the server's timeout closes it
            full = handshake(protocol)
            writer.write(full[:int(rng.integers(1, len(full) - 4))])
            await writer.drain()
            await _until_closed(reader, writer, DEADLINE_S)
            outcome["held_s"] = max(outcome["held_s"], round(time.monotonic() - t0))
    except (OSError, asyncio.IncompleteReadError, asyncio.TimeoutError) as exc:
        outcome[f"{KINDS[kind]}: {type(exc).__name__}"] += 1
    finally:
        writer.close()


async def _sample(pid: int, peak: list, stop: asyncio.Event) -> None:
    """The view process's largest RSS and fd count during the run, read each second."""
    while not stop.is_set():
        rss_mb, fds = proc_usage(pid)
        peak[:] = [max(peak[0], rss_mb), max(peak[1], fds)]
        try:
            await asyncio.wait_for(stop.wait(), 1.0)
        except asyncio.TimeoutError:
            pass


async def _fuzz(port: int, n: int, seed: int, concurrency: int, held: int,
                protocol: str, pid: int, peak: list) -> Counter:
    rng = np.random.default_rng(seed)
    outcome: Counter = Counter()
    stop = asyncio.Event()
    sampler = asyncio.ensure_future(_sample(pid, peak, stop))
    slots, held_slots = asyncio.Semaphore(concurrency), asyncio.Semaphore(held)
    tasks: set = set()
    for k in range(n):
        kind = len(KINDS) - 1 if k % HELD_EVERY == HELD_EVERY - 1 else k % (len(KINDS) - 1)
        sem = held_slots if kind == len(KINDS) - 1 else slots
        await sem.acquire()
        outcome[KINDS[kind]] += 1

        async def run(kind=kind, sem=sem):
            try:
                await asyncio.wait_for(_one(port, kind, rng, protocol, outcome), DEADLINE_S)
            except asyncio.TimeoutError:
                outcome[f"{KINDS[kind]}: our deadline"] += 1
            finally:
                sem.release()

        task = asyncio.ensure_future(run())
        tasks.add(task)
        task.add_done_callback(tasks.discard)
    await asyncio.gather(*tasks)
    stop.set()
    await sampler
    return outcome


async def _alive(port: int, protocol: str) -> tuple[bool, bool]:
    """(the page served, a client with the view's protocol given the scene)."""
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    writer.write(b"GET / HTTP/1.1\r\nHost: x\r\n\r\n")
    page = b" 200 " in (await asyncio.wait_for(_read_reply(reader), 10)).split(b"\r\n")[0]
    writer.close()
    reader, writer = await asyncio.open_connection("127.0.0.1", port, limit=1 << 24)
    writer.write(handshake(protocol))
    scene = False
    if b" 101 " in (await asyncio.wait_for(_read_reply(reader), 10)).split(b"\r\n")[0]:
        deadline = time.monotonic() + 10
        while not scene and time.monotonic() < deadline:
            opcode, payload = await asyncio.wait_for(read_frame(reader), 10)
            if opcode == 2:
                scene = any("waiting for the daemon" in str(m.get("props", m))
                            for m in viser_messages(payload))
    writer.close()
    return page, scene


def run_view(connections: int, seed: int, concurrency: int = 128, held: int = 64) -> dict:
    """A live view process, `connections` malformed connections, its stderr counted."""
    import viser

    from daemon.view.link import ViewLink
    from tests.test_natnet import free_ports

    port = free_ports(1)[0]
    err = tempfile.TemporaryFile()
    saved = os.dup(2)
    os.dup2(err.fileno(), 2)  # the view's process inherits this stderr
    protocol = f"viser-v{viser.__version__}"
    try:
        link = ViewLink("127.0.0.1", port)
        try:
            assert link._conn.poll(120) and "ready" in link._conn.recv()
            pid = link.process.pid
            before_ok = asyncio.run(_alive(port, protocol))
            usage0 = proc_usage(pid)
            t0 = time.perf_counter()
            peak = [0.0, 0]
            outcome = asyncio.run(_fuzz(port, connections, seed, concurrency, held, protocol,
                                        pid, peak))
            duration = time.perf_counter() - t0
            time.sleep(2.0)  # the server's last closes
            usage1 = proc_usage(pid)
            page, scene = asyncio.run(_alive(port, protocol))
            same = link.process.is_alive() and link.process.pid == pid
            time.sleep(1.0)  # the view's last lines
        finally:
            link.close()
    finally:
        os.dup2(saved, 2)
        os.close(saved)
    err.seek(0)
    text = err.read().decode("utf-8", "replace")
    lines = [ln for ln in text.splitlines() if ln.strip()]
    # the kind: what failed and the exception's type ("connection handler failed:
    # DecodeError"), as daemon.view.quiet tells kinds apart
    kinds = Counter(": ".join(ln.split(": ")[1:3]).rstrip(":") for ln in lines)
    most = max(kinds.values(), default=0)
    ok = page and scene and same and all(before_ok)
    return {"parser": "view (live)", "inputs": connections, "unhandled": 0 if ok else 1,
            "unhandled_kinds": {} if ok else {"page": page, "scene": scene, "same": same},
            "kinds_logged": len(kinds), "max_lines_per_kind": most,
            "max_lines_per_kind_per_s": most / max(duration, 1.0),
            "tracebacks": text.count("Traceback"), "duration_s": duration,
            "junk_per_s": connections / duration, "good_per_s": float("nan"),
            "concurrency": concurrency, "held": held, "outcomes": dict(outcome),
            "lines": lines[:50], "rss_mb": [usage0[0], usage1[0]],
            "fds": [usage0[1], usage1[1]], "peak_rss_mb": peak[0], "peak_fds": peak[1],
            "page": page, "scene": scene, "same_pid": same}
