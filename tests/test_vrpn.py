"""VRPN tracker server: wire layout, a hand-written client over both connection paths (TCP and
UDP connect-back), libmotioncapture's VRPN client, and a client that stops reading."""

from __future__ import annotations

import select
import socket
import struct
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
from test_natnet import Feeder, Scene, finish, run_motioncapture  # shared scene and client

from daemon.config.mocapd import SimConfig
from daemon.publish import packet, vrpn
from daemon.synthetic.scene import SimScene
from daemon.tracking.rigid import BodyDef

ROOT = Path(__file__).resolve().parents[1]

# ---- layout ---------------------------------------------------------------------------------

def test_cookie_and_message_layout():
    c = vrpn.cookie()
    assert len(c) == 24 and c.startswith(b"vrpn: ver. 07.35  0") and c[19:] == bytes(5)
    assert vrpn.check_cookie(b"vrpn: ver. 07.38  0".ljust(24, b"\0"))  # minor versions mix
    assert not vrpn.check_cookie(b"vrpn: ver. 06.10  0".ljust(24, b"\0"))
    m = vrpn.pack(3, 7, b"abcde", t_s=1700000000.25, seq=9)
    assert len(m) == 24 + 8  # payload padded to 8 bytes
    assert struct.unpack(">iiiiii", m[:24]) == (29, 1700000000, 250000, 3, 7, 9)
    d = vrpn.describe(vrpn.SENDER_DESCRIPTION, 2, "body0")
    assert struct.unpack_from(">iiiii", d)[3:] == (2, -1)
    assert d[24:24 + 10] == struct.pack(">i", 6) + b"body0\0"


def test_unpack_handles_partial_and_several_messages():
    stream = vrpn.pack(1, 2, b"x" * 9) + vrpn.pack(4, -2, b"") + vrpn.pack(5, 6, b"y" * 16)
    buf, got = bytearray(), []
    for k in range(0, len(stream), 7):  # as TCP may deliver it
        buf += stream[k:k + 7]
        got += vrpn.unpack_messages(buf)
    assert [(s, t, p) for s, t, p, _ in got] == [(1, 2, b"x" * 9), (4, -2, b""),
                                                 (5, 6, b"y" * 16)]
    assert not buf


def test_pose_messages_carry_tracked_bodies_only():
    scene = Scene()
    r = scene.frame(41)  # the last body is occluded
    m = vrpn.pose_messages(r, np.array([0, 1]), 1700000000.5)
    assert m.dtype.itemsize == 88 and len(m) == 1
    got = vrpn.unpack_messages(bytearray(m.tobytes()))
    sender, type_id, payload, t = got[0]
    assert (sender, type_id, len(payload), t) == (0, 0, 64, 1700000000.5)
    sensor, _, *values = struct.unpack(">ii7d", payload)
    assert sensor == 0
    np.testing.assert_array_equal(values[:3], r.poses.position[0])
    np.testing.assert_array_equal(values[3:], r.poses.quaternion[0])


# ---- a minimal VRPN client, written from the protocol description ---------------------------

class RawClient:
    """Connects (directly over TCP, or by lobbing a UDP request and accepting the server's
    call back), exchanges cookies, reads the server's descriptions and messages."""

    def __init__(self, port: int, lob: bool, udp: bool = False, read: bool = True,
                 rcvbuf: int | None = None) -> None:
        if lob:
            listener = socket.socket()
            listener.bind(("127.0.0.1", 0))
            listener.listen(1)
            listener.settimeout(5)
            u = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            u.sendto(f"127.0.0.1 {listener.getsockname()[1]}".encode() + b"\0",
                     ("127.0.0.1", port))
            self.sock, _ = listener.accept()
            listener.close()
            u.close()
        else:
            self.sock = socket.socket()
            if rcvbuf:
                self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
            self.sock.connect(("127.0.0.1", port))
        self.sock.settimeout(5)
        self.sock.sendall(vrpn.cookie())
        cookie = b""
        while len(cookie) < 24:
            cookie += self.sock.recv(24 - len(cookie))
        assert vrpn.check_cookie(cookie)
        self.senders, self.types, self.poses, self.pongs = {}, {}, [], 0
        self.buf = bytearray()
        self.udp = None
        if udp:  # offer a UDP port for the low-latency messages, as VRPN clients do
            self.udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            self.udp.bind(("127.0.0.1", 0))
            self.sock.sendall(vrpn.pack(self.udp.getsockname()[1], vrpn.UDP_DESCRIPTION,
                                        b"127.0.0.1\0"))
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        if read:
            self.thread.start()

    def ping(self, name: str) -> None:
        self.sock.sendall(vrpn.describe(vrpn.SENDER_DESCRIPTION, 5, name)
                          + vrpn.describe(vrpn.TYPE_DESCRIPTION, 3, vrpn.PING)
                          + vrpn.pack(5, 3))

    def _take(self, messages) -> None:
        for sender, type_id, payload, _t in messages:
            if type_id == vrpn.SENDER_DESCRIPTION:
                self.senders[sender] = payload[4:].split(b"\0")[0].decode()
            elif type_id == vrpn.TYPE_DESCRIPTION:
                self.types[sender] = payload[4:].split(b"\0")[0].decode()
            elif self.types.get(type_id) == vrpn.POS_QUAT:
                self.poses.append((self.senders[sender], struct.unpack(">ii7d", payload)[2:]))
            elif self.types.get(type_id) == vrpn.PONG:
                self.pongs += 1

    def _run(self) -> None:
        socks = [self.sock] + ([self.udp] if self.udp is not None else [])
        while not self.stop.is_set():
            for s in select.select(socks, [], [], 0.05)[0]:
                data = s.recv(65536)
                if s is self.udp:
                    self._take(vrpn.unpack_messages(bytearray(data)))
                elif not data:
                    return
                else:
                    self.buf += data
                    self._take(vrpn.unpack_messages(self.buf))

    def close(self) -> None:
        self.stop.set()
        if self.thread.is_alive():
            self.thread.join()
        self.sock.close()


def check_poses(poses, handed, scene: Scene, atol: float = 0.0) -> set:
    """Every (name, pose) received is that body's pose in a handed frame where it was
    tracked; the frames matched."""
    frames = sorted(handed)
    names = [b.name for b in scene.bodies]
    tables = [np.array([np.concatenate([handed[i].poses.position[j],
                                        handed[i].poses.quaternion[j]]) for i in frames])
              for j in range(len(names))]
    matched = set()
    for name, values in poses:
        j = names.index(name)
        d = np.nan_to_num(np.abs(tables[j] - np.asarray(values)), nan=1.0).max(axis=1)
        k = int(np.argmin(d))
        assert d[k] <= atol, f"{name}: pose not among the handed frames ({d[k]:.2e})"
        assert handed[frames[k]].poses.valid[j]
        matched.add((name, frames[k]))
    return matched


def test_raw_clients_over_tcp_and_connect_back_with_pings():
    scene = Scene()
    pub = vrpn.VrpnPublisher(scene.defs(), host="127.0.0.1", port=0)
    with Feeder(pub, scene) as feed:
        # a request to call back a port nobody listens on fails without holding anyone up
        dead = socket.socket()
        dead.bind(("127.0.0.1", 0))
        bogus = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        bogus.sendto(f"127.0.0.1 {dead.getsockname()[1]}".encode() + b"\0",
                     ("127.0.0.1", pub.port))
        bogus.sendto(b"garbage", ("127.0.0.1", pub.port))
        direct = RawClient(pub.port, lob=False)
        back = RawClient(pub.port, lob=True, udp=True)
        feed.wait_frames(100)
        back.ping("body1")
        direct.ping("nobody")  # not one of ours: no pong, as a VRPN server does
        feed.wait_frames(10)
        status = pub.status()
        direct.close()
        back.close()
    assert status["clients"] == 2 and status["errors"] == 0 and not pub._calling
    dead.close()
    bogus.close()
    for c in (direct, back):
        assert set(c.senders.values()) == {"body0", "body1"}
        assert {vrpn.POS_QUAT, vrpn.PONG} <= set(c.types.values())
        matched = check_poses(c.poses, feed.handed, scene)  # float64 on the wire: exact
        assert len(matched) >= 150
        assert {n for n, _ in matched} == {"body0", "body1"}
        # the occluded body is sent exactly in the frames where it was tracked
        frames0 = {f for n, f in matched if n == "body0"}
        frames1 = {f for n, f in matched if n == "body1"}
        assert frames1 == {f for f in frames0 if not scene.occluded(f)}
        assert len(frames0) > len(frames1) > 0
    assert back.pongs == 1 and direct.pongs == 0


def test_hostile_datagrams_never_stop_the_server_nor_send_it_elsewhere(caplog):
    """A port out of range once raised in the server thread and stopped VRPN for good; a
    datagram naming another host made the server connect there. Now every datagram is
    answered on its sender's address or ignored, and clients that come after are served."""
    import logging

    from hypothesis import HealthCheck, given, settings
    from hypothesis import strategies as st

    scene = Scene()
    pub = vrpn.VrpnPublisher(scene.defs(), host="127.0.0.1", port=0)
    u = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    with Feeder(pub, scene) as feed, caplog.at_level(logging.INFO, "mocapd"):
        for junk in (b"127.0.0.1 65536\0", b"127.0.0.1 -5\0", b"127.0.0.1 0\0",
                     b"\xff\xfe 12\0", b"1 2 3\0", b"", b"127.0.0.1 99999999999999999999\0"):
            u.sendto(junk, ("127.0.0.1", pub.port))

        @settings(max_examples=300, deadline=None,
                  suppress_health_check=[HealthCheck.function_scoped_fixture])
        @given(st.binary(max_size=64))
        def fuzz(data):
            u.sendto(data, ("127.0.0.1", pub.port))

        fuzz()
        # another address named in the datagram: called back on the sender's instead
        listener = socket.socket()
        listener.bind(("127.0.0.1", 0))
        listener.listen(1)
        listener.settimeout(5)
        u.sendto(f"127.0.0.2 {listener.getsockname()[1]}".encode() + b"\0",
                 ("127.0.0.1", pub.port))
        called, peer = listener.accept()
        called.close()
        listener.close()
        client = RawClient(pub.port, lob=True)
        feed.wait_frames(30)
        status = pub.status()
        client.close()
    u.close()
    assert peer[0] == "127.0.0.1"
    assert status["server_alive"] and status["server_restarts"] == 0
    assert len(client.poses) > 0
    ignored = [r for r in caplog.records if "ignoring a UDP datagram" in r.getMessage()]
    assert 1 <= len(ignored) <= 2  # rate-limited: one line per kind, not one per datagram
    assert not [r for r in caplog.records if r.exc_info]


def test_motioncapture_vrpn_clients_join_and_leave():
    """libmotioncapture's VRPN client: the first by UDP connect-back (poses over its UDP
    port), the second by tcp:// (poses over TCP) joining late and leaving early; both see
    every body's pose, hidden bodies drop out, the second changes nothing for the first."""
    scene = Scene()
    pub = vrpn.VrpnPublisher(scene.defs(), host="127.0.0.1", port=0)
    with Feeder(pub, scene) as feed:
        cfg = {"hostname": f"127.0.0.1:{pub.port}"}  # the port the server was given
        first = run_motioncapture("vrpn", cfg, 300)
        feed.wait_frames(80)
        second = run_motioncapture("vrpn", {"hostname": f"tcp://127.0.0.1:{pub.port}"}, 60)
        got_second = finish(second)
        got_first = finish(first)
        pongs = pub.pongs
    assert pub.status()["errors"] == 0 and pongs >= 2  # each tracker answered its pings
    for got, least in ((got_first, 150), (got_second, 25)):
        poses = [(n, v) for frame in got for n, v in frame.items()]
        matched = check_poses(poses, feed.handed, scene, atol=2e-6)  # float32 in the client
        assert {n for n, _ in matched} == {"body0", "body1"} and len(matched) > least
    # while body1 was hidden the client reported body0 alone
    assert any("body0" in f and "body1" not in f for f in got_first)
    assert any("body0" in f and "body1" in f for f in got_first)
    # the client polls at its own 100 Hz against our 100 Hz, so about every other poll is
    # empty; a client stalled by the second one's arrival or leaving would show far fewer
    assert sum(bool(f) for f in got_first) > 110


def test_a_client_that_stops_reading_is_dropped_and_the_others_go_on():
    scene = Scene(n_bodies=8)
    scene.occluded = lambda i: False
    pub = vrpn.VrpnPublisher(scene.defs(), host="127.0.0.1", port=0,
                             max_backlog_bytes=32_000)
    pub.open()
    try:
        stalled = RawClient(pub.port, lob=False, read=False, rcvbuf=4096)
        reader = RawClient(pub.port, lob=False)
        deadline = time.monotonic() + 10
        while sum(c.connected for c in pub.clients) < 2 and time.monotonic() < deadline:
            time.sleep(0.01)
        sent, frame = 0, scene.frame(0)
        while len(pub.clients) == 2 and time.monotonic() < deadline:
            pub.send(frame)
            sent += 1
        assert len(pub.clients) == 1, "the stalled client was never dropped"
        for _ in range(50):
            pub.send(frame)
        while len(reader.poses) < 8 * (sent + 50) and time.monotonic() < deadline + 5:
            time.sleep(0.01)
        assert len(reader.poses) == 8 * (sent + 50)  # every pose of every frame
        assert pub.status()["clients"] == 1
        stalled.close()
        reader.close()
    finally:
        pub.close()


# ---- the daemon end to end, configured by flags ------------------------------------------------

def test_mocapd_vrpn_flag_serves_poses_matching_the_simulator(tmp_path):
    """`mocapd start --sim --vrpn HOST:PORT`, read by libmotioncapture's VRPN client: the
    trackers are the scene's bodies by name, at the poses the daemon tracked (its own UDP
    packets) and at the simulator's true poses (0.2 px noise)."""
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.bind(("127.0.0.1", 0))
    rx.settimeout(0.1)
    tracked, stop = [], threading.Event()

    def drain():
        while not stop.is_set():
            try:
                tracked.append(packet.decode(rx.recv(65536)))
            except TimeoutError:
                pass

    reader = threading.Thread(target=drain, daemon=True)
    reader.start()
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    sim_args = dict(cameras=4, bodies=2, fps=100.0, noise_px=0.2, seed=5)
    n_frames = 500
    proc = subprocess.Popen(
        [sys.executable, "-m", "daemon.cli", "start", "--sim", "--sim-cameras", "4",
         "--sim-bodies", "2", "--sim-fps", "100", "--noise-px", "0.2", "--seed", "5",
         "--frames", str(n_frames), "--vrpn", f"127.0.0.1:{port}",
         "--udp", f"127.0.0.1:{rx.getsockname()[1]}",
         "--runtime-dir", tmp_path / "rt"],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 20
        while True:  # until mocapd listens (and drop this probe: it sent no cookie)
            try:
                socket.create_connection(("127.0.0.1", port), timeout=1).close()
                break
            except OSError:
                assert proc.poll() is None, proc.stderr.read()
                assert time.monotonic() < deadline, "mocapd never listened"
                time.sleep(0.1)
        got = finish(run_motioncapture("vrpn", {"hostname": f"127.0.0.1:{port}"}, 250),
                     timeout_s=30)
    finally:
        proc.terminate()
        proc.communicate(timeout=20)
        stop.set()
        reader.join()
        rx.close()
    # every pose received is one the daemon tracked for that body (float32 both sides)
    table = {name: np.array([np.concatenate([pk.position[k], pk.quaternion[k]])
                             for pk in tracked for k in np.flatnonzero(pk.ids == body_id)
                             if pk.valid[k]])
             for name, body_id in (("body0", 1), ("body1", 2))}
    for frame in got:
        for name, values in frame.items():
            off = np.abs(table[name] - np.array(values, np.float32)).max(axis=1).min()
            assert off < 1e-6, f"{name}: a pose the daemon did not send ({off:.1e})"
    scene = SimScene(SimConfig(**sim_args), n_frames=n_frames)
    truth = {b.name: b.poses[:, :3, 3] for b in scene.bodies_truth}
    errors = {name: [] for name in truth}
    for frame in got:
        for name, values in frame.items():
            # VRPN carries no frame number: the nearest true position along the path
            errors[name].append(np.min(np.linalg.norm(truth[name] - values[:3], axis=1)))
    for name, e in errors.items():
        assert len(e) > 50, name
        assert np.median(e) < 0.003  # metres; the daemon's own error here is ~1 mm RMS


def test_bad_protocol_flags_are_one_line_errors(mocapd_cli):
    for args, words in ((["--natnet", "eth0"], "--natnet"), (["--vrpn", "host:x"], "--vrpn"),
                        (["--natnet-up", "x"], "--natnet-up")):
        r = mocapd_cli("start", "--sim", "--frames", "1", *args)
        assert r.code == 2 and words in r.err and "Traceback" not in r.err
        assert len(r.err.strip().splitlines()) == 1


def test_a_client_speaking_nonsense_is_dropped_alone():
    scene = Scene()
    pub = vrpn.VrpnPublisher(scene.defs(), host="127.0.0.1", port=0)
    with Feeder(pub, scene) as feed:
        good = RawClient(pub.port, lob=False)
        bad = socket.create_connection(("127.0.0.1", pub.port))
        bad.sendall(b"HTTP/1.1 GET /\r\n\r\n" + bytes(40))  # not a VRPN cookie
        worse = RawClient(pub.port, lob=False, read=False)
        worse.sock.sendall(struct.pack(">iiiiii", 7, 0, 0, 0, 0, 0))  # length < a header
        deadline = time.monotonic() + 5
        while len(pub.clients) > 1 and time.monotonic() < deadline:
            time.sleep(0.02)
        n = len(good.poses)
        feed.wait_frames(20)
        assert len(pub.clients) == 1 and len(good.poses) > n
        good.close()
        worse.close()
        bad.close()


def test_a_reload_keeps_the_clients_connected():
    """The server a reload starts takes over the old one's sockets and clients: they stay
    connected (a VRPN client would otherwise take seconds to connect again), hear the new
    tracker list, and receive the new server's poses."""
    scene = Scene()
    old = vrpn.VrpnPublisher(scene.defs(), host="127.0.0.1", port=0)
    old.start()
    direct = RawClient(old.port, lob=False)
    back = RawClient(old.port, lob=True, udp=True)
    deadline = time.monotonic() + 5
    while sum(c.connected for c in old.clients) < 2 and time.monotonic() < deadline:
        time.sleep(0.01)
    renamed = [BodyDef("rover", 1, scene.bodies[0].markers_body, np.zeros(3))]
    new = vrpn.VrpnPublisher(renamed, host="127.0.0.1", port=old.port)
    new.start()
    assert old.handed_over and new.status()["clients"] == 2
    old.stop()
    with Feeder(new, scene, start=False) as feed:  # started above
        feed.wait_frames(30)
        deadline = time.monotonic() + 3
        while time.monotonic() < deadline and not all(
                any(n == "rover" for n, _ in c.poses) for c in (direct, back)):
            time.sleep(0.02)
    for c in (direct, back):
        assert c.senders[0] == "rover"  # described again by the new server
        assert any(n == "rover" for n, _ in c.poses)
        c.close()
