"""MAVLink soak: pymavlink as the autopilot on a UART (a pseudo-terminal) and on UDP,
against `mocapd start --sim`, for as long as asked (`--seconds 600` for the 10-minute
target).

The autopilot side, in this process, does on each link what ArduPilot and PX4 do: it sends
HEARTBEAT at 1 Hz and TIMESYNC requests (`--timesync-hz`), and reads everything mocapd
sends. It counts, per link: mocapd's messages and the gaps in their sequence numbers
(pymavlink's own loss count: what an autopilot reports as link loss), the HEARTBEATs and
their intervals, the TIMESYNC requests answered and their round trips, the
VISION_POSITION_ESTIMATE poses, and whether SET_GPS_GLOBAL_ORIGIN came once.

    python benchmarks/soak_mavlink.py [--seconds 600] [--fps 100] [--json out.json]
"""

from __future__ import annotations

import argparse
import os
import select
import socket
import subprocess
import sys
import tempfile
import time
import tty
from pathlib import Path

import numpy as np
from pymavlink.dialects.v20 import common as mavlink2

from calibkit.clitools import write_json
from daemon.service.console import print_table

ROOT = Path(__file__).resolve().parents[1]


class Side:
    """The autopilot's end of one link: writes with `send_bytes`, reads raw bytes."""

    def __init__(self, name: str, fd: int, send_bytes) -> None:
        self.name, self.fd = name, fd
        self.mav = mavlink2.MAVLink(self, srcSystem=1, srcComponent=1)
        self.parser = mavlink2.MAVLink(None)
        self.parser.robust_parsing = True
        self.send_bytes = send_bytes
        self.last_seq = None
        self.messages = self.gaps = self.lost = 0
        self.beats: list[float] = []
        self.asked: dict[int, int] = {}
        self.rtt_ms: list[float] = []
        self.poses = self.origins = 0

    def write(self, buf) -> None:
        self.send_bytes(bytes(buf))

    def take(self, data: bytes) -> None:
        now = time.monotonic_ns()
        for m in self.parser.parse_buffer(data) or ():
            if m.get_srcComponent() != 197:
                continue
            self.messages += 1
            seq = m.get_seq()
            if self.last_seq is not None and seq != (self.last_seq + 1) % 256:
                self.gaps += 1
                self.lost += (seq - self.last_seq - 1) % 256
            self.last_seq = seq
            kind = m.get_type()
            if kind == "HEARTBEAT":
                self.beats.append(now / 1e9)
            elif kind == "TIMESYNC" and m.tc1 != 0 and m.ts1 in self.asked:
                self.rtt_ms.append((now - self.asked.pop(m.ts1)) / 1e6)
            elif kind == "TIMESYNC" and m.tc1 == 0:
                self.mav.timesync_send(time.monotonic_ns(), m.ts1)
            elif kind == "VISION_POSITION_ESTIMATE":
                self.poses += 1
            elif kind == "SET_GPS_GLOBAL_ORIGIN":
                self.origins += 1

    def figures(self, seconds: float) -> dict:
        iv = np.diff(self.beats) if len(self.beats) > 1 else np.zeros(1)
        rtt = np.array(self.rtt_ms) if self.rtt_ms else np.full(1, np.nan)
        return {"messages": self.messages, "sequence_gaps": self.gaps,
                "messages_lost": self.lost, "heartbeats": len(self.beats),
                "heartbeat_hz": len(self.beats) / seconds,
                "heartbeat_interval_max_s": float(iv.max()),
                "heartbeat_interval_min_s": float(iv.min()),
                "timesync_answered": len(self.rtt_ms),
                "timesync_unanswered": len(self.asked),
                "timesync_rtt_ms_median": float(np.median(rtt)),
                "timesync_rtt_ms_p99": float(np.percentile(rtt, 99)),
                "poses": self.poses, "origins": self.origins}


def free_udp_port() -> int:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    return port


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=600.0)
    ap.add_argument("--fps", type=float, default=100.0, help="the simulated cameras' rate")
    ap.add_argument("--rate-hz", type=float, default=50.0, help="vision messages per second")
    ap.add_argument("--timesync-hz", type=float, default=4.0)
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)

    master, slave = os.openpty()
    tty.setraw(slave)
    uart = Side("uart", master, lambda b: os.write(master, b))
    udp_sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    udp_sock.bind(("127.0.0.1", free_udp_port()))
    udp_sock.setblocking(False)
    peer: list = []
    udp = Side("udp", udp_sock.fileno(), lambda b: peer and udp_sock.sendto(b, peer[0]))
    sides = {master: uart, udp_sock.fileno(): udp}

    runtime = tempfile.mkdtemp(prefix="soak-mavlink-")
    config = Path(runtime) / "mocapd.toml"
    config.write_text(
        f"[sim]\ncameras = 4\nbodies = 1\nfps = {args.fps}\n"
        f'[[mavlink]]\ndevice = "{os.ttyname(slave)}"\nbody = 1\nrate_hz = {args.rate_hz}\n'
        "origin = [47.3977, 8.5456, 488.0]\n"
        f'[[mavlink]]\ndevice = "udpout:127.0.0.1:{udp_sock.getsockname()[1]}"\nbody = 1\n'
        f"rate_hz = {args.rate_hz}\norigin = [47.3977, 8.5456, 488.0]\n")
    proc = subprocess.Popen([sys.executable, "-m", "daemon.cli", "start", "--config",
                             str(config), "--duration", str(args.seconds + 15),
                             "--runtime-dir", runtime], cwd=ROOT,
                            env=dict(os.environ, PYTHONPATH=str(ROOT)),
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    # wait for both links to speak before the clock starts
    deadline = time.monotonic() + 60
    while not (uart.messages and udp.messages):
        if proc.poll() is not None or time.monotonic() > deadline:
            print(f"mocapd did not start: {proc.stderr.read()}", file=sys.stderr)
            return 1
        for fd in select.select(list(sides), [], [], 0.1)[0]:
            _read(fd, sides, master, udp_sock, peer)
    for s in sides.values():  # count from here: the links are up
        s.__init__(s.name, s.fd, s.send_bytes)
    t0 = time.monotonic()
    next_beat = next_sync = t0
    period = 1.0 / args.timesync_hz
    try:
        while time.monotonic() - t0 < args.seconds and proc.poll() is None:
            now = time.monotonic()
            if now >= next_beat:
                for s in sides.values():
                    s.mav.heartbeat_send(2, 3, 0, 0, 4)
                next_beat += 1.0
            if now >= next_sync:
                for s in sides.values():
                    stamp = time.monotonic_ns()
                    s.asked[stamp] = stamp
                    s.mav.timesync_send(0, stamp)
                next_sync += period
            for fd in select.select(list(sides), [], [], 0.01)[0]:
                _read(fd, sides, master, udp_sock, peer)
        drain_end = time.monotonic() + 0.5
        while time.monotonic() < drain_end:
            for fd in select.select(list(sides), [], [], 0.05)[0]:
                _read(fd, sides, master, udp_sock, peer)
        seconds = time.monotonic() - t0
    finally:
        proc.terminate()
        err = proc.communicate(timeout=30)[1]
        os.close(master)
        os.close(slave)
        udp_sock.close()
    figures = {name: s.figures(seconds) for name, s in (("uart", uart), ("udp", udp))}
    rows = []
    for name, f in figures.items():
        rows.append([name, f["messages"], f["sequence_gaps"], f["messages_lost"],
                     f["heartbeats"], round(f["heartbeat_hz"], 3),
                     round(f["heartbeat_interval_max_s"], 3), f["timesync_answered"],
                     f["timesync_unanswered"], round(f["timesync_rtt_ms_median"], 3),
                     round(f["timesync_rtt_ms_p99"], 3), f["poses"], f["origins"]])
    print(f"{seconds:.0f} s against mocapd start --sim ({args.fps:g} fps, poses at "
          f"{args.rate_hz:g} Hz, TIMESYNC asked at {args.timesync_hz:g} Hz)")
    print_table(rows, ["link", "messages", "seq_gaps", "lost", "heartbeats", "hb_hz",
                       "hb_max_s", "ts_answered", "ts_open", "ts_rtt_med_ms",
                       "ts_rtt_p99_ms", "poses", "origins"])
    if args.json:
        write_json(args.json, {"config": vars(args), "seconds": seconds, "links": figures,
                               "mocapd_exit": proc.returncode, "mocapd_stderr_tail":
                               err.splitlines()[-5:]})
    return 0


def _read(fd, sides, master, udp_sock, peer) -> None:
    if fd == master:
        sides[fd].take(os.read(master, 65536))
        return
    try:
        data, addr = udp_sock.recvfrom(65536)
    except BlockingIOError:
        return
    if not peer:
        peer.append(addr)  # answer where mocapd sends from, as an autopilot does
    sides[fd].take(data)


if __name__ == "__main__":
    sys.exit(main())
