"""NatNet and VRPN output: encoding cost and the latency each protocol adds, vs mocapd's UDP.

Frames: 10 rigid bodies of 5 markers moving as the simulator moves them, plus 20 loose
markers (70 tracked markers), handed to each publisher at `--fps` from this process. A
receiver thread in the same process reads the output on loopback and stamps each frame's
arrival; latency is arrival minus the moment the frame was handed to the publisher
(Publisher.submit), so it covers the queue hand-off, encoding, the send calls and the
loopback, which is what a protocol adds on top of tracking.

Protocols: mocapd's own UDP packet (the baseline), NatNet 4.1 frames by multicast and by
unicast (a keep-alive subscriber), VRPN Pos_Quat messages over the client's UDP port and
over TCP. The receivers are minimal raw sockets, not the real clients, so that the client
library's own polling (libmotioncapture's VRPN loop sleeps to 100 Hz) does not hide what
the server adds. Encoding is timed separately, one frame at a time, `--repeats` times.

Each protocol runs `--runs` times, interleaved; the figures are medians over runs of each
run's median (and 99th percentile); ratios are against the UDP baseline of the same run.

    python benchmarks/bench_protocols.py [--frames 600] [--fps 240] [--runs 3] [--json out.json]
"""

from __future__ import annotations

import argparse
import select
import socket
import struct
import sys
import threading
import time

import numpy as np

from calibkit.clitools import print_table, write_json
from calibkit.synthetic import sim
from daemon.capture.pipeline import FrameResult
from daemon.publish import natnet, vrpn
from daemon.publish.packet import decode
from daemon.publish.udp import UdpPublisher, result_packet
from daemon.tracking.rigid import BodyDef, BodyPoses, quaternion_xyzw
from daemon.tracking.tracker import TrackFrame

N_BODIES, K, N_LOOSE = 10, 5, 20


def make_frames(n: int, fps: float):
    _, bodies = sim.rigid_body_motion(N_BODIES, n, fps, 4.0, K, seed=1)
    loose = np.random.default_rng(2).uniform(-1.5, 1.5, (N_LOOSE, 3)) + [0, 0, 1.5]
    defs = [BodyDef(b.name, b.id, b.markers_body, np.zeros(3)) for b in bodies]
    R = np.stack([b.poses[:, :3, :3] for b in bodies], 1)  # (F, B, 3, 3)
    t = np.stack([b.poses[:, :3, 3] for b in bodies], 1)
    layout = np.stack([b.markers_body for b in bodies])
    world = np.einsum("fbij,bkj->fbki", R, layout) + t[:, :, None, :]
    ids = np.arange(N_BODIES * K + N_LOOSE) + 1
    tracks = ids[:N_BODIES * K].reshape(N_BODIES, K)
    frames = []
    for f in range(n):
        xyz = np.concatenate([world[f].reshape(-1, 3), loose])
        poses = BodyPoses(np.array([b.id for b in bodies]), np.ones(N_BODIES, bool), t[f],
                          R[f], quaternion_xyzw(R[f]), np.full(N_BODIES, 4e-4),
                          np.full(N_BODIES, K), tracks)
        tf = TrackFrame(ids, xyz, np.ones(len(ids), bool), np.full(len(ids), 3),
                        np.zeros((len(ids), 0), int), np.zeros(len(ids), int))
        frames.append(FrameResult(f, 0, 0, 0, np.zeros(0, int), np.zeros((0, 2)), tf, poses))
    return defs, frames


def free_port(kind=socket.SOCK_DGRAM) -> int:
    s = socket.socket(socket.AF_INET, kind)
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    return port


# ---- receivers: (sockets, frame number of a datagram or stream chunk) -------------------------

class Receiver:
    """Reads datagrams (or a TCP stream) on a thread; stamps arrival per frame number."""

    def __init__(self, socks, frames_of) -> None:
        self.socks, self.frames_of = socks, frames_of
        self.arrival: dict[int, int] = {}
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        while not self.stop.is_set():
            for s in select.select(self.socks, [], [], 0.05)[0]:
                data = s.recv(65536)
                now = time.monotonic_ns()
                for f in self.frames_of(data, s):
                    self.arrival.setdefault(f, now)

    def close(self) -> None:
        self.stop.set()
        self.thread.join()
        for s in self.socks:
            s.close()


def udp_setup(defs):
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.bind(("127.0.0.1", 0))
    pub = UdpPublisher([("127.0.0.1", rx.getsockname()[1])])
    return pub, Receiver([rx], lambda d, _s: [decode(d).frame])


def _natnet_frame(data, _):
    return [struct.unpack_from("<i", data, 4)[0]] if data[:2] == b"\x07\x00" else []


def natnet_multicast_setup(defs):
    cmd, data = free_port(), free_port()
    pub = natnet.NatNetPublisher(defs, "127.0.0.1", cmd, data, multicast=True, ttl=0)
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    rx.bind((pub.group, data))
    rx.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP,
                  socket.inet_aton(pub.group) + socket.inet_aton("127.0.0.1"))
    return pub, Receiver([rx], _natnet_frame)


def natnet_unicast_setup(defs):
    cmd, data = free_port(), free_port()
    pub = natnet.NatNetPublisher(defs, "127.0.0.1", cmd, data, multicast=False)
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.bind(("127.0.0.1", 0))
    pub.start()  # the keep-alive needs the command port open
    rx.sendto(struct.pack("<HH", natnet.NAT_KEEPALIVE, 0), ("127.0.0.1", cmd))
    return pub, Receiver([rx], _natnet_frame)


def vrpn_connect(pub, udp: bool, origin_ns: int) -> Receiver:
    """A raw VRPN client: cookie over TCP, optionally a UDP port for the poses."""
    tcp = socket.create_connection(("127.0.0.1", pub.port))
    tcp.sendall(vrpn.cookie())
    tcp.settimeout(2)
    got = b""
    while len(got) < vrpn.COOKIE_SIZE:
        got += tcp.recv(vrpn.COOKIE_SIZE - len(got))
    socks = [tcp]
    if udp:
        u = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        u.bind(("127.0.0.1", 0))
        tcp.sendall(vrpn.pack(u.getsockname()[1], vrpn.UDP_DESCRIPTION, b"127.0.0.1\0"))
        socks.append(u)
    stream = bytearray()

    def frames_of(data, sock):
        """Frame numbers of the Pos_Quat messages (their time field carries the frame)."""
        if sock is tcp:
            stream.extend(data)
            msgs = vrpn.unpack_messages(stream)
        else:
            msgs = vrpn.unpack_messages(bytearray(data))
        return [round((t * 1e9 - origin_ns) / 1e6) for _s, type_id, _p, t in msgs
                if type_id == 0]

    return Receiver(socks, frames_of)


def run(name, setup, defs, frames, fps) -> dict:
    """Hand every frame to the publisher at fps; latency per frame received."""
    wall = time.time_ns() - time.monotonic_ns()
    base_ns = time.monotonic_ns()
    if name.startswith("vrpn"):
        udp = name == "vrpn/udp"
        pub = vrpn.VrpnPublisher(defs, "127.0.0.1", free_port(socket.SOCK_STREAM))
        pub.start()
        rx = vrpn_connect(pub, udp, base_ns + wall)
        while sum(c.connected for c in pub.clients) < 1 or (udp and pub.clients[0].udp is None):
            time.sleep(0.01)
    else:
        pub, rx = setup(defs)
        if not pub.connected:
            pub.start()
    time.sleep(0.1)
    handed = {}
    period = 1.0 / fps
    due = time.monotonic()
    for r in frames:
        now = time.monotonic_ns()
        # VRPN's message time is the frame time on the wall clock: 1 ms per frame number
        r.t_ns = base_ns + r.frame * 1_000_000
        r.arrival_ns = now
        handed[r.frame] = now
        pub.submit(r)
        due += period
        time.sleep(max(0.0, due - time.monotonic()))
    time.sleep(0.2)
    rx.close()
    pub.stop()
    lat = np.array([rx.arrival[f] - handed[f] for f in handed if f in rx.arrival]) * 1e-6
    return {"received": len(lat) / len(frames), "median_ms": float(np.median(lat)),
            "p99_ms": float(np.percentile(lat, 99)), "dropped": pub.dropped}


def encode_us(defs, frames, repeats: int) -> dict:
    senders = np.arange(N_BODIES)
    enc = {
        "udp": lambda r: result_packet(r),
        "natnet": lambda r: natnet.message(natnet.NAT_FRAMEOFDATA, natnet.frame_payload(r)),
        "vrpn": lambda r: vrpn.pose_messages(r, senders, 1.7e9).tobytes(),
    }
    out = {}
    for name, f in enc.items():
        times = []
        for _ in range(repeats):
            t0 = time.perf_counter_ns()
            for r in frames[:200]:
                size = len(f(r))
            times.append((time.perf_counter_ns() - t0) / 200 / 1e3)
        out[name] = {"encode_us": float(np.median(times)), "bytes": size}
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=600)
    ap.add_argument("--fps", type=float, default=240.0)
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)
    defs, frames = make_frames(args.frames, args.fps)
    enc = encode_us(defs, frames, args.repeats)
    setups = {"udp": udp_setup, "natnet/multicast": natnet_multicast_setup,
              "natnet/unicast": natnet_unicast_setup, "vrpn/udp": None, "vrpn/tcp": None}
    runs = {k: [] for k in setups}
    for i in range(args.runs):
        for name, setup in setups.items():
            runs[name].append(run(name, setup, defs, frames, args.fps))
            print(f"run {i + 1}/{args.runs} {name}: {runs[name][-1]['median_ms']:.3f} ms",
                  file=sys.stderr)
    figures = {}
    rows = []
    for name in setups:
        med = [r["median_ms"] for r in runs[name]]
        ratio = [r["median_ms"] / b["median_ms"] for r, b in zip(runs[name], runs["udp"],
                                                                 strict=True)]
        e = enc[name.split("/")[0]]
        figures[name] = {"median_ms": float(np.median(med)),
                         "p99_ms": float(np.median([r["p99_ms"] for r in runs[name]])),
                         "ratio_to_udp": float(np.median(ratio)),
                         "received": float(np.min([r["received"] for r in runs[name]])),
                         "encode_us": e["encode_us"], "bytes_per_frame": e["bytes"]}
        f = figures[name]
        rows.append([name, round(f["encode_us"], 1), f["bytes_per_frame"],
                     round(f["median_ms"], 3), round(f["p99_ms"], 3),
                     round(f["ratio_to_udp"], 2), round(100 * f["received"], 1)])
    print(f"{N_BODIES} bodies x {K} markers + {N_LOOSE} loose markers, {args.frames} frames "
          f"at {args.fps:.0f} fps, {args.runs} runs")
    print_table(rows, ["protocol", "encode_us", "bytes", "latency_med_ms", "latency_p99_ms",
                       "x_udp", "received_%"])
    if args.json:
        write_json(args.json, {"config": vars(args), "protocols": figures})
    return 0


if __name__ == "__main__":
    sys.exit(main())
