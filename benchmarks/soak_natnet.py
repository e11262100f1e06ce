"""NatNet soak: OptiTrack's own sample client (`python -m natnetsdk`) against
`mocapd start --sim`, unicast or multicast, for as long as asked (`--seconds 600` for the
10-minute target); and NatNet's echo clock synchronisation measured beside it.

Both run in a network namespace of their own (`unshare -n`, loopback only): the sample
client has Motive's ports (1510, 1511) written in, which must not meet another server on
this machine, and on Linux it receives multicast only when bound to the wildcard address,
for which the namespace routes the multicast range to loopback. Nothing leaves it.

The sample is driven as a person would: `c` (configuration: it asks the bitstream
version), `s` (data descriptions), with `--switch-versions` in unicast `3` then `4`
(bitstream 3.1, then 4.1 again), and `q` at the end. It prints "MoCap Frame: N" for each
frame it has parsed; an error in
parsing prints ERROR/WARNING or a traceback. Counted: frames parsed, frame numbers missing
between the first and the last (UDP loss), duplicates, error lines, and the namespace's UDP
receive-buffer drops (datagrams sent that a too-slow reader's full buffer refused).

Echo: a socket sends NAT_ECHOREQUEST with its monotonic clock every `--echo-ms`; the
server's answer carries its clock on arrival. On loopback both clocks are the same, so the
offset a client computes (server stamp minus the request's midpoint) is the error of the
method; NatNet clients take the sample of least round trip in a window, as here (10).

    python benchmarks/soak_natnet.py [--seconds 600] [--mode unicast|multicast] [--json out]
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import socket
import struct
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
NAT_CONNECT, NAT_ECHOREQUEST, NAT_ECHORESPONSE = 0, 12, 13


def in_namespace(argv) -> int:
    """Run this script again inside a new network namespace with loopback up."""
    if shutil.which("unshare") is None or shutil.which("ip") is None:
        print("soak_natnet: needs unshare (util-linux) and ip (iproute2)", file=sys.stderr)
        return 2
    env = dict(os.environ, SOAK_NATNET_NETNS="1", PYTHONPATH=str(ROOT))
    return subprocess.call(["unshare", "-n", sys.executable, __file__, *argv], env=env)


def loopback_up() -> None:
    subprocess.run(["ip", "link", "set", "lo", "up"], check=True)
    subprocess.run(["ip", "route", "add", "224.0.0.0/4", "dev", "lo"], check=True)


def wait_for_server(port: int, proc, timeout_s: float = 60.0) -> None:
    probe = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    probe.settimeout(0.3)
    deadline = time.monotonic() + timeout_s
    try:
        while True:
            probe.sendto(struct.pack("<HH", NAT_CONNECT, 0), ("127.0.0.1", port))
            try:
                if probe.recv(1024)[:2] == b"\x01\x00":
                    return
            except OSError:
                if proc.poll() is not None or time.monotonic() > deadline:
                    raise RuntimeError(f"mocapd did not answer: {proc.stderr.read()}") \
                        from None
    finally:
        probe.close()


class Echo:
    """NAT_ECHOREQUEST every period; offsets and round trips of the answers."""

    def __init__(self, port: int, period_s: float) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.settimeout(0.5)
        self.port, self.period_s = port, period_s
        self.samples: list[tuple[int, int]] = []  # (rtt ns, offset ns)
        self.lost = 0
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        while not self.stop.wait(self.period_s):
            sent = time.monotonic_ns()
            self.sock.sendto(struct.pack("<HHQ", NAT_ECHOREQUEST, 8, sent),
                             ("127.0.0.1", self.port))
            try:
                data = self.sock.recv(64)
            except OSError:
                self.lost += 1
                continue
            back = time.monotonic_ns()
            msg_id, size, stamp, server = struct.unpack_from("<HHQQ", data)
            if msg_id == NAT_ECHORESPONSE and stamp == sent:
                self.samples.append((back - sent, server - (sent + back) // 2))

    def figures(self, window: int = 10) -> dict:
        self.stop.set()
        self.thread.join()
        s = np.array(self.samples, dtype=np.int64).reshape(-1, 2)
        best = [w[np.argmin(w[:, 0])] for w in np.array_split(s, max(1, len(s) // window))
                if len(w)]
        off_ms = np.abs(np.array([b[1] for b in best])) / 1e6
        return {"echoes": len(s), "echoes_lost": self.lost,
                "rtt_ms_median": float(np.median(s[:, 0]) / 1e6) if len(s) else None,
                "offset_ms_median_abs": float(np.median(off_ms)) if len(off_ms) else None,
                "offset_ms_max_abs": float(off_ms.max()) if len(off_ms) else None}


def udp_receive_buffer_drops() -> int:
    """Datagrams this network namespace's kernel dropped because a socket's receive buffer
    was full (its reader too slow): frames the server sent that a client never read."""
    lines = [line.split() for line in Path("/proc/net/snmp").read_text().splitlines()
             if line.startswith("Udp:")]
    return int(lines[1][lines[0].index("RcvbufErrors")])


def daemon_side(runtime: Path) -> dict:
    """What the daemon says it did: sets it skipped to stay live when it fell behind (their
    frame numbers never go out), frames its NatNet output sent and pushed out of its queue."""
    from daemon.service.control import request

    st = request(runtime, {"cmd": "status"})
    natnet = next((o for o in st["outputs"] if "natnet" in o["name"].lower()), {})
    return {"daemon_skipped_behind": (st.get("multiplexer") or {}).get("skipped_behind"),
            "natnet_sent": natnet.get("sent"), "natnet_queue_dropped": natnet.get("dropped")}


def run(args) -> dict:
    loopback_up()
    drops_before = udp_receive_buffer_drops()
    runtime = Path(tempfile.mkdtemp(prefix="soak-natnet-"))
    multicast = args.mode == "multicast"
    (runtime / "mocapd.toml").write_text(
        f"[sim]\ncameras = 4\nbodies = {args.bodies}\nfps = {args.fps}\n"
        f'[natnet]\ninterface = "127.0.0.1"\nmulticast = {str(multicast).lower()}\n')
    mocapd = subprocess.Popen([sys.executable, "-m", "daemon.cli", "start", "--config",
                               str(runtime / "mocapd.toml"), "--duration",
                               str(args.seconds + 60), "--runtime-dir", str(runtime)],
                              cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                              text=True)
    try:
        wait_for_server(1510, mocapd)
        echo = Echo(1510, args.echo_ms / 1000)
        client = "0.0.0.0" if multicast else "127.0.0.1"
        attempts = 0
        while True:
            attempts += 1
            sample = subprocess.Popen([sys.executable, "-u", "-m", "natnetsdk", "127.0.0.1",
                                       client, "m" if multicast else "u"],
                                      stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                      stderr=subprocess.STDOUT, text=True)
            out: list[str] = []
            reader = threading.Thread(target=lambda s=sample, o=out: o.extend(s.stdout),
                                      daemon=True)
            reader.start()
            # the sample parses frames as version 0.0 until the server description comes;
            # by multicast a frame can come first and kill its data thread (Motive's too):
            # started again until it has said the server's version with no traceback
            # before (on a loaded machine its start alone can take seconds)
            deadline = time.monotonic() + 60
            while (time.monotonic() < deadline and sample.poll() is None
                   and not any("NatNetVersion" in line for line in out)):
                time.sleep(0.1)
            time.sleep(0.2)  # a frame parsed as 0.0 just before is said by now
            if not any("Traceback" in line for line in out) or attempts >= 10:
                break
            sample.kill()
            sample.wait()
            reader.join(5)
        steps = [(2.0, "c"), (4.0, "s")]
        if args.switch_versions and not multicast:
            steps += [(args.seconds * 0.4, "3"), (args.seconds * 0.7, "4")]
        t0 = time.monotonic()
        for at, key in steps:
            time.sleep(max(0.0, t0 + at - time.monotonic()))
            sample.stdin.write(key + "\n")
            sample.stdin.flush()
        time.sleep(max(0.0, t0 + args.seconds - time.monotonic()))
        # what the sample printed while it ran: the SDK's own threads can trip over their
        # sockets being closed as it quits (EBADF in its command thread), which is the
        # sample's shutdown, not our stream; those lines are counted apart
        running = len(out)
        sample.stdin.write("q\n")
        sample.stdin.flush()
        # it says "shutdown called" as it quits: waited for (5 s at most), then a moment to end
        quit_by = time.monotonic() + 5
        while (sample.poll() is None and time.monotonic() < quit_by
               and not any("shutdown called" in line for line in out)):
            time.sleep(0.05)
        try:
            sample.wait(timeout=0.5)
        except subprocess.TimeoutExpired:
            # its unicast data socket never receives (frames come to the command socket),
            # and on Linux closing it does not wake its thread from recvfrom: it never ends
            sample.kill()
            sample.wait()
        reader.join(5)
        clock = echo.figures()
        buffer_drops = udp_receive_buffer_drops() - drops_before
        daemon = daemon_side(runtime)
    finally:
        mocapd.terminate()
        mocapd.communicate(timeout=30)
    frames = [int(m.group(1)) for line in out if (m := re.match(r"MoCap Frame: (\d+)", line))]
    def error_lines(lines):
        return [line.strip() for line in lines
                if re.search(r"ERROR|WARNING|Traceback|Exception|Error:", line)]

    errors = error_lines(out[:running])
    errors_at_quit = error_lines(out[running:])
    f = np.array(frames)
    span = int(f.max() - f.min() + 1) if len(f) else 0
    settled = np.unique(f[f >= f.min() + args.settle_s * args.fps]) if len(f) else f
    missing_settled = int(settled.max() - settled.min() + 1 - len(settled)) if len(settled) \
        else 0
    versions = sorted({line.split("NatNetVersion", 1)[1].strip() for line in out
                       if "NatNetVersion" in line})
    if args.log:
        Path(args.log).write_text("".join(out))
    return {"mode": args.mode, "seconds": args.seconds, "frames_parsed": len(frames),
            "frame_span": span, "frames_missing": span - len(set(frames)),
            f"frames_missing_after_{args.settle_s:g}s": missing_settled,
            "duplicates": len(frames) - len(set(frames)), "receive_buffer_drops": buffer_drops,
            "error_lines": errors[:20],
            "errors": len(errors), "errors_at_quit": errors_at_quit[:20],
            "versions_seen": versions,
            "bitstream_changes": sum("Bitstream version at" in line for line in out),
            "quit_cleanly": any("shutdown called" in line for line in out),
            "sample_starts": attempts, **daemon, **clock}


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=600.0)
    ap.add_argument("--mode", choices=("unicast", "multicast"), default="unicast")
    ap.add_argument("--fps", type=float, default=100.0)
    ap.add_argument("--bodies", type=int, default=2)
    ap.add_argument("--echo-ms", type=float, default=100.0)
    ap.add_argument("--settle-s", type=float, default=5.0,
                    help="frames missing are also counted from this long after the first")
    ap.add_argument("--json", default=None)
    ap.add_argument("--log", default=None, help="write the sample's output here")
    ap.add_argument("--switch-versions", action="store_true",
                    help="unicast: also press 3 (bitstream 3.1) and later 4 (4.1); the "
                         "sample parses in the new version from the moment it asks, so "
                         "frames already on their way can be misread")
    args = ap.parse_args(argv)
    if not os.environ.get("SOAK_NATNET_NETNS"):
        return in_namespace(argv)
    from calibkit.clitools import write_json
    from daemon.service.console import print_table

    fig = run(args)
    print(f"natnetsdk sample, {args.mode}, {args.seconds:g} s against mocapd start --sim "
          f"({args.fps:g} fps, {args.bodies} bodies)")
    print_table([[k, v if not isinstance(v, list) else "; ".join(map(str, v)) or "-"]
                 for k, v in fig.items() if k not in ("mode", "seconds")], ["what", "value"])
    if args.json:
        write_json(args.json, {"config": vars(args), **fig})
    return 0 if fig["errors"] == 0 and fig["quit_cleanly"] else 1


if __name__ == "__main__":
    sys.exit(main())
