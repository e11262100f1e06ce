"""MAVLink output against pymavlink playing the autopilot: over a pseudo-terminal (a UART)
and loopback UDP; sequence numbers, HEARTBEAT, TIMESYNC both ways, origin and home once;
the serial line budget; `mocapd start --mavlink udpout:...` and `mocapd status`."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import threading
import time
import tty
from pathlib import Path

import numpy as np
import pytest
from pymavlink.dialects.v20 import common as mavlink2

from daemon.config.mocapd import parse_config
from daemon.config.outputs import MavlinkOut, SerialOut
from daemon.publish.line import fit_mavlink, fit_serial, serial_frame_bytes
from daemon.publish.mavlink import MavlinkPublisher
from daemon.tracking.rigid import BodyPoses, matrix_from_quaternion

ROOT = Path(__file__).resolve().parents[1]
ORIGIN = (47.3977, 8.5456, 488.0)


class Frame:
    """A FrameResult's fields a publisher reads: one valid body, id 1."""

    def __init__(self, i: int) -> None:
        q = np.array([[0.0, 0.0, np.sin(0.2), np.cos(0.2)]])
        self.frame, self.t_ns = i, time.monotonic_ns()
        self.arrival_ns = self.t_ns
        self.poses = BodyPoses(np.array([1]), np.array([True]), np.array([[0.5, -1.0, 1.2]]),
                               matrix_from_quaternion(q), q, np.array([1e-4]),
                               np.array([4]), np.zeros((1, 4), np.int64))


class FdFile:
    def __init__(self, fd: int) -> None:
        self.fd = fd

    def write(self, buf) -> None:
        os.write(self.fd, bytes(buf))


class PtyAutopilot:
    """pymavlink as an ArduPilot on the far end of a UART (the pty's master side): it
    sends HEARTBEAT at 1 Hz and TIMESYNC requests, answers our TIMESYNC requests, and
    keeps every message it receives with its arrival time."""

    def __init__(self, master: int) -> None:
        self.master = master
        self.mav = mavlink2.MAVLink(FdFile(master), srcSystem=1, srcComponent=1)
        self.parser = mavlink2.MAVLink(None)
        self.got: list[tuple[float, object]] = []
        self.asked: dict[int, float] = {}
        self.answers: list[tuple[int, int]] = []  # (our ts1, their tc1)
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        next_beat = next_sync = time.monotonic()
        while not self.stop.is_set():
            now = time.monotonic()
            if now >= next_beat:
                self.mav.heartbeat_send(2, 3, 0, 0, 3)  # quadrotor, ArduPilot, standby
                next_beat += 1.0
            if now >= next_sync:
                stamp = time.monotonic_ns()
                self.asked[stamp] = now
                self.mav.timesync_send(0, stamp)
                next_sync += 0.25
            import select
            if select.select([self.master], [], [], 0.02)[0]:
                data = os.read(self.master, 4096)
                for m in self.parser.parse_buffer(data) or ():
                    self.got.append((time.monotonic(), m))
                    if m.get_type() == "TIMESYNC":
                        if m.tc1 == 0:
                            self.mav.timesync_send(time.monotonic_ns() + 7, m.ts1)
                        else:
                            self.answers.append((m.ts1, m.tc1))

    def of(self, kind: str) -> list:
        return [(t, m) for t, m in self.got if m.get_type() == kind]


def _run_frames(pub, seconds: float, hz: float = 50.0) -> None:
    t_end = time.monotonic() + seconds
    i = 0
    while time.monotonic() < t_end:
        pub.submit(Frame(i))
        i += 1
        time.sleep(1.0 / hz)


def test_a_uart_autopilot_hears_heartbeats_gapless_sequences_timesync_and_the_origin():
    master, slave = os.openpty()
    tty.setraw(slave)  # a UART carries bytes: no echo, no line editing (as pyserial sets it)
    ap = PtyAutopilot(master)
    pub = MavlinkPublisher(os.ttyname(slave), body=1, baud=115200, rate_hz=30.0,
                           frame="flu", origin=ORIGIN)
    try:
        pub.start()
        deadline = time.monotonic() + 3
        while not pub.connected and time.monotonic() < deadline:  # opening flushes input
            time.sleep(0.01)
        ap.thread.start()
        _run_frames(pub, 4.2)
        status = pub.status()
    finally:
        pub.stop()
        ap.stop.set()
        ap.thread.join()
        os.close(master)
        os.close(slave)
    ours = [m for _, m in ap.got if m.get_srcComponent() == 197]
    assert len(ours) == len(ap.got) > 100
    seqs = np.array([m.get_seq() for m in ours])
    assert np.all(np.diff(seqs) % 256 == 1), "a gap in the sequence numbers"
    assert seqs[0] == 0 and len(set(seqs.tolist())) > 100
    beats = np.array([t for t, _ in ap.of("HEARTBEAT")])
    assert 4 <= len(beats) <= 6 and np.all(np.abs(np.diff(beats) - 1.0) < 0.25)
    hb = ap.of("HEARTBEAT")[0][1]
    assert (hb.type, hb.autopilot) == (18, 8)  # an onboard controller, not an autopilot
    # every TIMESYNC request of the autopilot answered with its stamp and our clock
    answered = {m.ts1 for _, m in ap.of("TIMESYNC") if m.tc1 != 0}
    asked = sorted(ap.asked)[:-2]  # the last ones may still be on the way when we stop
    assert len(asked) >= 12 and set(asked) <= answered
    # the origin and home, once, where configured
    (_, origin), = ap.of("SET_GPS_GLOBAL_ORIGIN")
    (_, home), = ap.of("SET_HOME_POSITION")
    for m in (origin, home):
        assert (m.target_system, m.latitude, m.longitude, m.altitude) == (
            1, 473977000, 85456000, 488000)
    poses = [m for _, m in ap.of("VISION_POSITION_ESTIMATE")]
    assert len(poses) > 90 and poses[0].x == pytest.approx(0.5) and poses[0].y == \
        pytest.approx(1.0)  # FLU (0.5, -1.0, 1.2) -> NED (0.5, 1.0, -1.2)
    # what `mocapd status` shows of the autopilot and our own requests' round trips
    assert status["autopilot"]["autopilot"] == "ardupilotmega"
    assert status["autopilot"]["type"] == "quadrotor" and status["autopilot"]["heartbeats"] >= 4
    assert status["timesync_answered"] >= 12 and status["timesync_rtt_ms"] < 100
    assert ap.answers and status["origin_sent"] == 1 and status["errors"] == 0


def _udp_port() -> int:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    return port


@pytest.mark.parametrize("we_listen", [False, True])
def test_udp_both_ways_with_a_mavutil_autopilot(we_listen):
    """udpout: we send to the autopilot's port; udpin: we listen and answer whoever sends
    (as MAVProxy's `--out` reaches a companion)."""
    from pymavlink import mavutil

    port = _udp_port()
    if we_listen:
        ours, theirs = f"udpin:127.0.0.1:{port}", f"udpout:127.0.0.1:{port}"
    else:
        ours, theirs = f"udpout:127.0.0.1:{port}", f"udpin:127.0.0.1:{port}"
    ap = mavutil.mavlink_connection(theirs, source_system=1, source_component=1)
    ap.mav = mavlink2.MAVLink(ap, srcSystem=1, srcComponent=1)  # MAVLink 2 both ways
    ap.WIRE_PROTOCOL_VERSION = "2.0"
    pub = MavlinkPublisher(ours, body=1, rate_hz=50.0)
    got, stamps = [], {}
    try:
        pub.start()
        deadline = time.monotonic() + 3
        while not got:  # a udpin side answers only peers it has heard: start with our beat
            if we_listen:
                ap.mav.heartbeat_send(2, 12, 0, 0, 3)
            m = ap.recv_match(blocking=True, timeout=0.1)
            if m is not None:
                got.append(m)
            assert time.monotonic() < deadline, "no heartbeat from us"
        t_end = time.monotonic() + 3.2
        i = next_beat = 0
        while time.monotonic() < t_end:
            now = time.monotonic()
            if now >= next_beat:
                ap.mav.heartbeat_send(2, 12, 0, 0, 3)  # quadrotor, PX4
                stamp = time.monotonic_ns()
                stamps[stamp] = now
                ap.mav.timesync_send(0, stamp)
                next_beat = now + 1.0
            pub.submit(Frame(i))
            i += 1
            m = ap.recv_match(blocking=True, timeout=0.02)
            while m is not None:
                got.append(m)
                m = ap.recv_match(blocking=False)
        status = pub.status()
    finally:
        pub.stop()
        ap.close()
    ours_msgs = [m for m in got if m.get_srcComponent() == 197]
    seqs = np.array([m.get_seq() for m in ours_msgs])
    assert len(seqs) > 100 and np.all(np.diff(seqs) % 256 == 1)
    assert 3 <= sum(m.get_type() == "HEARTBEAT" for m in ours_msgs) <= 5
    answers = {m.ts1 for m in ours_msgs if m.get_type() == "TIMESYNC" and m.tc1 > 0}
    assert set(sorted(stamps)[:-1]) <= answers
    assert sum(m.get_type() == "VISION_POSITION_ESTIMATE" for m in ours_msgs) > 100
    assert status["autopilot"]["autopilot"] == "px4" and status["errors"] == 0


def test_a_uart_that_is_not_there_is_retried_and_reported(tmp_path):
    pub = MavlinkPublisher(str(tmp_path / "ttyACM9"), body=1, rate_hz=50.0)
    pub.retry_s = 0.1
    pub.start()
    for i in range(50):  # a count, not a time: a loaded machine submits fewer in a time
        pub.submit(Frame(i))
        time.sleep(0.01)
    deadline = time.monotonic() + 60
    while pub.errors < 3 and time.monotonic() < deadline:  # three tries to open, 0.1 s apart
        time.sleep(0.05)
    pub.stop()
    assert "cannot open" in pub.last_error and pub.errors >= 3 and pub.sent == 0
    assert pub.dropped > 10  # poses dropped while the link is down, submit never blocked


# ---- the serial line budget -----------------------------------------------------------------

def test_three_bodies_at_100_hz_do_not_fit_115200_baud():
    assert serial_frame_bytes(3) == 136  # 24 + 3 x 36 + 2, COBS code byte, delimiter
    with pytest.raises(ValueError) as err:
        fit_serial(SerialOut("/dev/ttyUSB0", 115200, 100.0), 3, fps=240)
    text = str(err.value)
    assert "13.6 kB/s" in text and "11.5 kB/s" in text and "at most 84" in text
    assert "230400 fits" in text
    out, note = fit_serial(SerialOut("/dev/ttyUSB0", 115200), 3, fps=240)  # auto
    assert out.rate_hz == 76 and "76 Hz" in note  # 90 % of the line
    assert fit_serial(SerialOut("/dev/ttyUSB0", 115200), 1, fps=240)[0].rate_hz == 100
    assert fit_serial(SerialOut("/dev/ttyUSB0", 921600, 0.0), 3, fps=240)[0].rate_hz == 0
    with pytest.raises(ValueError, match="every frame"):  # 240 fps x 136 bytes
        fit_serial(SerialOut("/dev/ttyUSB0", 230400, 0.0), 3, fps=240)


def test_mavlink_budget_counts_heartbeat_and_timesync():
    with pytest.raises(ValueError, match="57600 baud carries 5.8 kB/s"):
        fit_mavlink(MavlinkOut("/dev/ttyS1", 1, 57600, "odometry", rate_hz=50.0), fps=240)
    out, note = fit_mavlink(MavlinkOut("/dev/ttyS1", 1, 57600, "odometry"), fps=240)
    assert out.rate_hz == 19 and "auto" in note  # (5184 - 301) B/s / 245-byte frames
    out, _ = fit_mavlink(MavlinkOut("udpout:127.0.0.1:14550", 1), fps=240)
    assert out.rate_hz == 50  # a network link: no budget


def test_a_rate_that_does_not_fit_refuses_to_start(tmp_path, start_refused):
    cfg = tmp_path / "mocapd.toml"
    cfg.write_text('[[serial]]\ndevice = "/dev/ttyUSB7"\nrate_hz = 100\n[sim]\ncameras = 3\n')
    line = start_refused(cfg)
    assert "serial[0] (/dev/ttyUSB7): 3 bodies" in line and "at most 84" in line


def test_mavlink_tables_and_their_errors():
    cfg = parse_config({"mavlink": [{"device": "udpout:127.0.0.1:14550", "body": 2,
                                     "origin": [47.0, 8.0, 400], "rate_hz": "auto"},
                                    {"device": "/dev/ttyACM0", "body": 1, "rate_hz": 30}]})
    a, b = cfg.mavlink
    assert (a.device, a.origin, a.rate_hz) == ("udpout:127.0.0.1:14550", (47.0, 8.0, 400.0),
                                               None)
    assert (b.device, b.rate_hz, b.origin) == ("/dev/ttyACM0", 30.0, None)
    from calibkit.core.errors import UserError

    for bad, words in (({"device": "udpout:nowhere", "body": 1}, "mavlink[0].device"),
                       ({"device": "tcpin:0.0.0.0:5760", "body": 1}, "not supported"),
                       ({"device": "/dev/x", "body": 1, "origin": [91, 0, 0]},
                        "mavlink[0].origin"),
                       ({"device": "/dev/x", "body": 1, "rate_hz": "fast"},
                        "mavlink[0].rate_hz")):
        with pytest.raises(UserError, match=words.replace("[", r"\[").replace("]", r"\]")):
            parse_config({"mavlink": [bad]})


# ---- the daemon ------------------------------------------------------------------------------

def test_mocapd_start_serves_an_autopilot_over_udp_and_status_shows_it(tmp_path, mocapd_cli):
    from pymavlink import mavutil

    port = _udp_port()
    ap = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", source_system=1,
                                    source_component=1)
    ap.mav = mavlink2.MAVLink(ap, srcSystem=1, srcComponent=1)
    ap.WIRE_PROTOCOL_VERSION = "2.0"
    runtime = tmp_path / "rt"
    proc = subprocess.Popen([sys.executable, "-m", "daemon.cli", "start", "--sim",
                             "--sim-cameras", "4", "--sim-bodies", "1", "--sim-fps", "60",
                             "--mavlink", f"udpout:127.0.0.1:{port}", "--mavlink-body", "1",
                             "--mavlink-origin", "47.3977,8.5456,488", "--duration", "20",
                             "--runtime-dir", str(runtime)], cwd=ROOT,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    got = []
    try:
        deadline = time.monotonic() + 30
        while not any(m.get_type() == "VISION_POSITION_ESTIMATE" for m in got):
            assert proc.poll() is None and time.monotonic() < deadline, proc.stderr.read()
            m = ap.recv_match(blocking=True, timeout=0.2)
            if m is not None:
                got.append(m)
        t_end = time.monotonic() + 2.5
        next_beat = 0.0
        while time.monotonic() < t_end:
            if time.monotonic() >= next_beat:
                ap.mav.heartbeat_send(2, 3, 0, 0, 4)  # an active ArduPilot quadrotor
                next_beat = time.monotonic() + 0.5
            m = ap.recv_match(blocking=True, timeout=0.05)
            if m is not None:
                got.append(m)
        r = mocapd_cli("status", "--runtime-dir", runtime, "--json", tmp_path / "st.json")
        assert r.code == 0, r.err
    finally:
        proc.terminate()
        proc.communicate(timeout=20)
        ap.close()
    out = next(o for o in json.loads((tmp_path / "st.json").read_text())["outputs"]
               if o["name"].startswith("mavlink:"))
    assert out["autopilot"]["autopilot"] == "ardupilotmega" and out["origin_sent"] == 1
    assert "autopilot 1/1 (ardupilotmega, quadrotor, active)" in r.out
    seqs = np.array([m.get_seq() for m in got])
    assert np.all(np.diff(seqs) % 256 == 1)
    poses = [m for m in got if m.get_type() == "VISION_POSITION_ESTIMATE"]
    assert len(poses) > 50
    xyz = np.array([[m.x, m.y, m.z] for m in poses])
    assert np.all(np.isfinite(xyz)) and np.all(np.abs(xyz) < 4.0)
    assert np.all(np.diff([m.usec for m in poses]) > 0)
    assert any(m.get_type() == "SET_GPS_GLOBAL_ORIGIN" for m in got)
