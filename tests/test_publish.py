"""Pose packets, serial framing, the C header, MAVLink frames and the publisher machinery."""

from __future__ import annotations

import os
import shutil
import socket
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from daemon.publish import packet
from daemon.publish.base import Publisher
from daemon.publish.mavlink import mavlink_message, to_ned
from daemon.publish.serial import SerialPublisher
from daemon.publish.udp import UdpPublisher

HEADER_H = Path(__file__).resolve().parents[1] / "daemon" / "publish" / "mocapd_packet.h"


def _bodies(n, rng):
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return dict(ids=np.arange(1, n + 1), valid=rng.random(n) > 0.3,
                markers=rng.integers(3, 9, n), position=rng.normal(size=(n, 3)),
                quaternion=q, error_m=rng.random(n) * 1e-3)


def test_packet_round_trip_and_layout():
    rng = np.random.default_rng(0)
    b = _bodies(5, rng)
    data = packet.encode(123456, 987654321012, 1500, **b)
    assert len(data) == 24 + 5 * 36
    p = packet.decode(data)
    assert (p.frame, p.t_ns, p.latency_ns) == (123456, 987654321012, 1500)
    np.testing.assert_array_equal(p.ids, b["ids"])
    np.testing.assert_array_equal(p.valid, b["valid"])
    np.testing.assert_allclose(p.position, b["position"], rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(p.quaternion, b["quaternion"], rtol=1e-6, atol=1e-7)
    # the documented offsets: magic, count, frame at 4, t_ns at 8, first body's x at 28
    assert data[:2] == b"MC"[::-1] or int.from_bytes(data[:2], "little") == 0x434D
    assert data[3] == 5
    assert int.from_bytes(data[4:8], "little") == 123456
    assert np.frombuffer(data[28:32], "<f4")[0] == np.float32(b["position"][0, 0])


def test_packet_decode_rejects_garbage():
    good = packet.encode(1, 2, 3, **_bodies(2, np.random.default_rng(1)))
    for bad in (good[:10], b"XX" + good[2:], good[:-1], good + b"\0"):
        with pytest.raises(ValueError):
            packet.decode(bad)


def test_crc16_check_value():
    assert packet.crc16(b"123456789") == 0x29B1  # CRC-16/CCITT-FALSE's check value


@settings(max_examples=200, deadline=None)
@given(st.binary(max_size=700))
def test_cobs_round_trip_has_no_zero(data):
    enc = packet.cobs_encode(data)
    assert b"\x00" not in enc
    assert packet.cobs_decode(enc) == data
    assert len(enc) <= len(data) + len(data) // 254 + 2


def test_cobs_known_vectors():
    # the examples of Cheshire & Baker's paper (as listed on Wikipedia)
    assert packet.cobs_encode(b"\x00") == b"\x01\x01"
    assert packet.cobs_encode(b"\x00\x00") == b"\x01\x01\x01"
    assert packet.cobs_encode(b"\x11\x22\x00\x33") == b"\x03\x11\x22\x02\x33"
    assert packet.cobs_encode(b"\x11\x00\x00\x00") == b"\x02\x11\x01\x01\x01"
    assert packet.cobs_encode(bytes(range(1, 255))) == b"\xff" + bytes(range(1, 255))


def test_serial_frame_detects_corruption():
    payload = packet.encode(7, 8, 9, **_bodies(3, np.random.default_rng(2)))
    frame = packet.serial_frame(payload)
    assert frame.endswith(b"\x00") and b"\x00" not in frame[:-1]
    assert packet.read_serial_frame(frame[:-1]) == payload
    broken = bytearray(frame[:-1])
    broken[10] ^= 0x40 if broken[10] != 0x40 else 0x01
    with pytest.raises(ValueError):
        packet.read_serial_frame(bytes(broken))


@pytest.mark.skipif(shutil.which("cc") is None, reason="no C compiler on this machine")
def test_c_header_decodes_a_serial_frame(tmp_path):
    rng = np.random.default_rng(3)
    b = _bodies(3, rng)
    frame = packet.serial_frame(packet.encode(42, 123456789, 777, **b))[:-1]
    src = tmp_path / "t.c"
    src.write_text(f"""
#include <stdio.h>
#include "{HEADER_H}"
int main(void) {{
    uint8_t in[4096], dec[4096]; size_t n = fread(in, 1, sizeof in, stdin);
    size_t m = mocapd_cobs_decode(in, n, dec); size_t len = mocapd_check_crc(dec, m);
    mocapd_header_t h; int count = mocapd_parse(dec, len, &h);
    if (count < 0) {{ puts("bad"); return 1; }}
    printf("%u %lld %u %d\\n", h.frame, (long long)h.t_ns, h.latency_ns, count);
    for (int i = 0; i < count; i++) {{ mocapd_body_t b; mocapd_body(dec, i, &b);
        printf("%u %u %.6f %.6f %.6f %.6f\\n", b.id, b.flags, b.pos[0], b.pos[1], b.pos[2],
               b.quat[3]); }}
    return 0;
}}""")
    exe = tmp_path / "t"
    subprocess.run(["cc", "-std=c99", "-Wall", "-Werror", "-o", str(exe), str(src)], check=True)
    out = subprocess.run([str(exe)], input=frame, capture_output=True, check=True).stdout
    lines = out.decode().split("\n")
    assert lines[0] == "42 123456789 777 3"
    for i in range(3):
        f = lines[1 + i].split()
        assert int(f[0]) == b["ids"][i] and int(f[1]) == int(b["valid"][i])
        np.testing.assert_allclose([float(v) for v in f[2:5]], b["position"][i], atol=1e-5)
        assert abs(float(f[5]) - b["quaternion"][i, 3]) < 1e-5


def test_ned_conversion_of_an_enu_pose():
    # a body at x=1 (east), y=2 (north), z=3 (up), turned 90 degrees left (yaw +90 in ENU)
    Rz = np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])
    p, R = to_ned(np.array([1.0, 2, 3]), Rz, "enu")
    np.testing.assert_allclose(p, [2, 1, -3])
    # body x axis (forward) pointed north in ENU -> north in NED: first column (1, 0, 0)
    np.testing.assert_allclose(R[:, 0], [1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)


@pytest.mark.parametrize("message", ["vision_position_estimate", "odometry", "att_pos_mocap"])
def test_mavlink_messages_decode_with_pymavlink(message):
    from pymavlink.dialects.v20 import common as mavlink2

    mav = mavlink2.MAVLink(None, srcSystem=1, srcComponent=197)
    yaw = np.radians(30)
    Rz = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]])
    msg = mavlink_message(mav, message, 5_000_000, [0.5, -1.0, 1.2], Rz, "flu")
    got = mavlink2.MAVLink(None).parse_buffer(msg.pack(mav))
    assert len(got) == 1
    m = got[0]
    # FLU world -> NED: (x, -y, -z); a left (counter-clockwise) yaw is negative in NED
    assert (m.x, m.y, m.z) == pytest.approx((0.5, 1.0, -1.2), abs=1e-6)
    if message == "vision_position_estimate":
        assert m.yaw == pytest.approx(-yaw, abs=1e-6)
        assert np.isnan(m.covariance[0])
    else:
        w, x, y, z = (m.q[i] for i in range(4))
        assert abs(w) == pytest.approx(np.cos(yaw / 2), abs=1e-6)
        assert np.sign(z) == -np.sign(w)  # negative yaw
        cov = m.pose_covariance if message == "odometry" else m.covariance
        assert np.isnan(cov[0])


class _Result:
    def __init__(self, i, bodies):
        from daemon.tracking.rigid import BodyPoses, matrix_from_quaternion

        self.frame, self.t_ns, self.arrival_ns = i, time.monotonic_ns(), time.monotonic_ns()
        q = bodies["quaternion"]
        self.poses = BodyPoses(bodies["ids"], bodies["valid"], bodies["position"],
                               matrix_from_quaternion(q), q, bodies["error_m"],
                               bodies["markers"], np.zeros((len(q), 4), np.int64))


def test_udp_publisher_sends_decodable_packets():
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.bind(("127.0.0.1", 0))
    rx.settimeout(2.0)
    pub = UdpPublisher([rx.getsockname()], bodies=[2, 3])
    pub.start()
    b = _bodies(4, np.random.default_rng(4))
    pub.submit(_Result(5, b))
    p = packet.decode(rx.recv(2048))
    pub.stop()
    rx.close()
    assert p.frame == 5
    np.testing.assert_array_equal(p.ids, [2, 3])
    np.testing.assert_allclose(p.position, b["position"][1:3], atol=1e-6)


def test_udp_publisher_multicast_on_loopback():
    group = "239.255.77.2"
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    rx.bind(("", 0))
    rx.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP,
                  socket.inet_aton(group) + socket.inet_aton("127.0.0.1"))
    rx.settimeout(2.0)
    pub = UdpPublisher([(group, rx.getsockname()[1])], ttl=0, interface="127.0.0.1")
    pub.start()
    b = _bodies(2, np.random.default_rng(6))
    pub.submit(_Result(9, b))
    p = packet.decode(rx.recv(2048))
    pub.stop()
    rx.close()
    assert p.frame == 9 and p.ids.tolist() == [1, 2]


class _Stuck(Publisher):
    name = "stuck"

    def send(self, result):
        time.sleep(0.05)


def test_a_slow_output_never_blocks_submit():
    pub = _Stuck()
    pub.start()
    t0 = time.perf_counter()
    for i in range(200):
        pub.submit(i)
    elapsed = time.perf_counter() - t0
    pub.stop(timeout=1.0)
    assert elapsed < 0.05  # 200 submits, while the worker handles one per 50 ms
    assert pub.dropped >= 200 - 8 - 2  # queue of 8: the rest were pushed out, oldest first


def test_serial_publisher_to_a_pseudo_terminal_that_stops_reading():
    master, slave = os.openpty()
    try:
        pub = SerialPublisher(os.ttyname(slave), 115200, rate_hz=0)
        pub.start()
        b = _bodies(2, np.random.default_rng(5))
        pub.submit(_Result(1, b))
        data = b""
        deadline = time.monotonic() + 60
        while not data.endswith(b"\x00") and time.monotonic() < deadline:
            data += os.read(master, 4096)
        p = packet.decode(packet.read_serial_frame(data[:-1]))
        assert p.frame == 1
        # now nobody reads: the pty fills up, writes time out, submit still never blocks
        # (a submit that waited for the write would take the write's timeout each time:
        # thousands of seconds for these 3000, against a deadline a loaded machine meets)
        t0 = time.perf_counter()
        for i in range(3000):
            pub.submit(_Result(i, b))
            time.sleep(0.0002)
        assert time.perf_counter() - t0 < 120.0
        deadline = time.monotonic() + 60
        while pub.errors == 0 and time.monotonic() < deadline:
            time.sleep(0.05)
        assert pub.errors >= 1 and "send failed" in pub.last_error
        pub.stop(timeout=1.0)
    finally:
        os.close(master)
        os.close(slave)


# ---- labelled markers in the packet (a marker set configured) ---------------------------------

def _markers(k, rng, set_size=41):
    return (set_size, rng.permutation(set_size)[:k], rng.random(k),
            rng.normal(size=(k, 3)))


def test_packet_with_labelled_markers_round_trip_and_layout():
    rng = np.random.default_rng(5)
    b = _bodies(2, rng)
    set_size, index, conf, xyz = _markers(7, rng)
    data = packet.encode(9, 10, 11, **b, labelled=(set_size, index, conf, xyz))
    assert len(data) == 24 + 2 * 36 + 4 + 7 * 16
    assert int.from_bytes(data[20:24], "little") == packet.HAS_MARKERS  # header flags
    end = 24 + 2 * 36
    assert int.from_bytes(data[end:end + 2], "little") == 7
    assert int.from_bytes(data[end + 2:end + 4], "little") == 41
    first = end + 4  # index u16, confidence u8, flags u8, then x y z
    assert int.from_bytes(data[first:first + 2], "little") == index[0]
    assert data[first + 2] == round(conf[0] * 255) and data[first + 3] == 0
    assert np.frombuffer(data[first + 4:first + 16], "<f4").tolist() == \
        xyz[0].astype(np.float32).tolist()
    p = packet.decode(data)
    np.testing.assert_array_equal(p.ids, b["ids"])
    assert p.has_markers and p.set_size == 41
    np.testing.assert_array_equal(p.marker_index, index)
    np.testing.assert_allclose(p.marker_confidence, conf, atol=0.5 / 255 + 1e-7)
    np.testing.assert_allclose(p.marker_position, xyz, rtol=1e-6, atol=1e-6)
    # an empty section still says a marker set is configured
    p0 = packet.decode(packet.encode(1, 2, 3, **b, labelled=(41, [], [], np.zeros((0, 3)))))
    assert p0.has_markers and p0.set_size == 41 and len(p0.marker_index) == 0
    # an old packet decodes as before, with no markers
    old = packet.decode(packet.encode(1, 2, 3, **b))
    assert not old.has_markers and old.marker_position.shape == (0, 3)
    for bad in (data[:-1], data + b"\0", data[:end + 2]):
        with pytest.raises(ValueError):
            packet.decode(bad)


def test_a_41_marker_packet_with_ten_bodies_fits_the_ethernet_mtu():
    rng = np.random.default_rng(6)
    data = packet.encode(1, 2, 3, **_bodies(10, rng), labelled=_markers(41, rng))
    assert len(data) + 28 <= 1500  # IPv4 and UDP headers: one unfragmented datagram


@pytest.mark.skipif(shutil.which("cc") is None, reason="no C compiler on this machine")
def test_c_header_decodes_labelled_markers_and_old_packets(tmp_path):
    rng = np.random.default_rng(7)
    b = _bodies(2, rng)
    set_size, index, conf, xyz = _markers(5, rng)
    new = packet.encode(5, 6, 7, **b, labelled=(set_size, index, conf, xyz))
    old = packet.encode(5, 6, 7, **b)
    src = tmp_path / "m.c"
    src.write_text(f"""
#include <stdio.h>
#include "{HEADER_H}"
int main(void) {{
    uint8_t buf[4096]; size_t n = fread(buf, 1, sizeof buf, stdin);
    mocapd_header_t h; int count = mocapd_parse(buf, n, &h);
    if (count < 0) {{ puts("bad"); return 1; }}
    uint16_t set_size = 0; int k = mocapd_marker_count(buf, &h, &set_size);
    printf("%d %d %u\\n", count, k, set_size);
    for (int i = 0; i < k; i++) {{ mocapd_marker_t m; mocapd_marker(buf, &h, i, &m);
        printf("%u %u %.6f %.6f %.6f\\n", m.index, m.confidence, m.pos[0], m.pos[1],
               m.pos[2]); }}
    return 0;
}}""")
    exe = tmp_path / "m"
    subprocess.run(["cc", "-std=c99", "-Wall", "-Werror", "-o", str(exe), str(src)], check=True)
    out = subprocess.run([str(exe)], input=new, capture_output=True, check=True).stdout
    lines = out.decode().split("\n")
    assert lines[0] == "2 5 41"
    for i in range(5):
        f = lines[1 + i].split()
        assert int(f[0]) == index[i] and int(f[1]) == round(conf[i] * 255)
        np.testing.assert_allclose([float(v) for v in f[2:5]], xyz[i], atol=1e-5)
    out = subprocess.run([str(exe)], input=old, capture_output=True, check=True).stdout
    assert out.decode().split("\n")[0] == "2 0 0"
    bad = subprocess.run([str(exe)], input=new[:-1], capture_output=True)
    assert bad.returncode == 1


class _Collecting(Publisher):
    """Opens when asked (or fails to), keeps what it is sent."""

    name = "collect"

    def __init__(self, fail_open: bool = False) -> None:
        super().__init__(queue_size=64, retry_s=30.0)
        self.fail_open, self.opened, self.got = fail_open, 0, []

    def open(self) -> None:
        self.opened += 1
        if self.fail_open:
            raise OSError("no such device")

    def send(self, result) -> None:
        self.got.append(result)


def test_stop_flushes_frames_queued_before_the_output_ever_opened():
    """A recording stopped before its worker thread ran (a loaded machine) is still
    written whole: the output is opened at stop and every queued frame sent."""
    from types import SimpleNamespace

    pub = _Collecting()
    frames = [SimpleNamespace(arrival_ns=i) for i in range(5)]
    for f in frames:
        pub.submit(f)
    pub._stop = True  # stop asked before the worker's first turn
    pub.start()
    pub._thread.join(5)
    assert pub.opened == 1 and pub.got == frames


def test_stop_does_not_wait_on_an_output_that_failed_to_open():
    pub = _Collecting(fail_open=True)
    pub.start()
    pub.submit(0)
    deadline = time.monotonic() + 5
    while pub.opened == 0 and time.monotonic() < deadline:
        time.sleep(0.01)
    for i in range(1, 4):
        pub.submit(i)
    t0 = time.monotonic()
    pub.stop(timeout=5)
    assert time.monotonic() - t0 < 2 and not pub._thread.is_alive()
    assert pub.opened == 1 and pub.got == []
