"""Capture nodes over Zenoh: the wire encoding, the clock estimate, and nodes as separate
processes feeding one daemon over loopback (tracking, clocks, a node killed and
restarted, poses out)."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from calibkit.core.errors import UserError
from daemon.config.mocapd import parse_config
from daemon.nodes.clock import NodeClock
from daemon.nodes.settings import parse_camera_list, parse_node_config
from daemon.publish import zenoh_wire as wire

ROOT = Path(__file__).resolve().parents[1]


# ---- wire --------------------------------------------------------------------------------------

def test_blobs_message_round_trips_and_refuses_what_it_is_not():
    rng = np.random.default_rng(1)
    uv = rng.uniform(0, 640, (7, 2))
    area, peak = rng.uniform(2, 50, 7), rng.uniform(10, 255, 7)
    data = wire.encode_blobs(0xDEADBEEF, 12, 40, -5, 10**15, 10**15 + 7, 2**41, 39, uv,
                             area, peak)
    assert len(data) == wire.BLOBS_HEAD.size + 7 * 16
    m = wire.decode_blobs(data)
    assert (m.boot, m.seq, m.index, m.t_ns, m.arrival_ns, m.sent_ns, m.device_time_ns,
            m.device_frame_id) == (0xDEADBEEF, 12, 40, -5, 10**15, 10**15 + 7, 2**41, 39)
    np.testing.assert_allclose(m.uv, uv, atol=1e-4 * 640)  # float32 on the wire
    np.testing.assert_allclose(m.area, area.astype(np.float32))
    empty = wire.decode_blobs(wire.encode_blobs(1, 0, 0, 0, 0, 0, -1, -1, np.zeros((0, 2)),
                                                np.zeros(0), np.zeros(0)))
    assert empty.uv.shape == (0, 2) and empty.device_time_ns == -1
    with pytest.raises(wire.WireError, match="says 7 blobs"):
        wire.decode_blobs(data[:-3])
    with pytest.raises(wire.WireError, match="not a version"):
        wire.decode_blobs(b"XX" + data[2:])


def _frames(rng, counts):
    return [(f"cam{k}".encode(), 100 + k, 10**12 + k, 10**12 + 50 + k, 2**40 + k, 7 + k,
             rng.uniform(0, 640, (n, 2)), rng.uniform(2, 50, n), rng.uniform(10, 255, n))
            for k, n in enumerate(counts)]


def test_blob_sets_message_round_trips_and_refuses_what_it_is_not():
    rng = np.random.default_rng(2)
    frames = _frames(rng, [5, 0, 12, 1])
    data = wire.encode_sets(0xFEEDF00D, 77, 10**12 + 999, frames)
    got = wire.decode_sets(data)
    assert [n for n, _ in got] == ["cam0", "cam1", "cam2", "cam3"]
    for (_, m), f in zip(got, frames, strict=True):
        assert (m.boot, m.seq, m.sent_ns) == (0xFEEDF00D, 77, 10**12 + 999)
        assert (m.index, m.t_ns, m.arrival_ns, m.device_time_ns, m.device_frame_id) == f[1:6]
        assert m.uv.shape == (len(f[6]), 2)
        np.testing.assert_allclose(m.uv, f[6], atol=1e-4 * 640)  # float32 on the wire
        np.testing.assert_allclose(m.area, f[7].astype(np.float32))
        np.testing.assert_allclose(m.peak, f[8].astype(np.float32))
    assert wire.decode_sets(wire.encode_sets(1, 0, 0, [])) == []
    with pytest.raises(wire.WireError, match="does not hold"):
        wire.decode_sets(data[:-3])
    with pytest.raises(wire.WireError, match="does not hold"):
        wire.decode_sets(data + b"\0")
    with pytest.raises(wire.WireError, match="ends inside"):
        wire.decode_sets(data[:wire.SETS_HEAD.size + 10])
    with pytest.raises(wire.WireError, match="not a version"):
        wire.decode_sets(wire.encode_blobs(1, 0, 0, 0, 0, 0, -1, -1, np.zeros((0, 2)),
                                           np.zeros(0), np.zeros(0)))


class _Pub:
    """Stands in for a Zenoh publisher: keeps what is put, with when."""

    def __init__(self):
        self.sent = []

    def put(self, data):
        self.sent.append((time.monotonic_ns(), wire.decode_sets(data)))


class _Session:
    def __init__(self):
        self.pub = _Pub()

    def declare_publisher(self, key, **_):
        return self.pub


def _sample(camera, index, arrival):
    from daemon.capture.sources import CameraSample

    uv = np.full((2, 2), float(camera))
    return CameraSample(camera, index, arrival, arrival, uv, np.ones(2), np.ones(2), -1, -1)


def test_a_node_sends_one_set_per_trigger_as_soon_as_its_last_frame_is_in():
    """Four cameras: each trigger's four frames leave in one message when the fourth
    comes, not before; a camera whose frame does not come is waited for set_wait_ms, the
    set leaves marked short without it, and its late frame leaves alone the moment it
    comes; a camera's next frame closes the set its last one is in; a camera silent past
    STALE_NS is no longer waited for."""
    from daemon.nodes.node import STALE_NS, NodeTime, SetPublisher

    period, t0 = 4_166_667, time.monotonic_ns()

    def add(k, g):
        sets.add(k, _sample(k, g, t0 + g * period + k * 1000))

    def names(i=-1):
        return [n for n, _ in sent[i][1]]

    session = _Session()
    # 50 ms: long enough that a loaded machine's pauses between two adds below do not time
    # a set out (3 ms did, at load 15), short of STALE_NS (100 ms)
    wait_ns = 50_000_000
    sets = SetPublisher(session, "k", 5, NodeTime(), ["a", "b", "c", "d"], wait_ns=wait_ns)
    sets.start()
    sent = session.pub.sent
    try:
        for k in range(4):  # the first trigger: cameras not known yet are not waited for
            add(k, 0)
        end = time.monotonic() + 5.0  # what waited for a camera has timed out
        while sum(len(f) for _, f in sent) < 4 and time.monotonic() < end:
            time.sleep(0.001)
        assert sorted(n for _, f in sent for n, _ in f) == ["a", "b", "c", "d"]
        first, short = len(sent), sets.short
        for g in (1, 2):  # all four known now: one message per trigger
            for k in (2, 0, 3, 1):
                before = len(sent)
                add(k, g)
                assert len(sent) == before + (k == 1)  # out with its last frame only
        assert [[n for n, _ in f] for _, f in sent[first:]] == [["a", "b", "c", "d"]] * 2
        # camera d is late at trigger 3: the set waits wait_ns, then leaves without it
        opened = time.monotonic_ns()
        for k in (0, 1, 2):
            add(k, 3)
        end = time.monotonic() + 5.0
        while len(sent) == first + 2 and time.monotonic() < end:
            time.sleep(0.0005)
        assert names() == ["a", "b", "c"] and sets.short == short + 1
        assert sent[-1][1][0][1].flags & wire.SET_SHORT
        assert wait_ns <= sent[-1][0] - opened < 5_000_000_000
        add(3, 3)  # d's late frame of that trigger leaves at once, alone
        assert names() == ["d"] and sent[-1][1][0][1].index == 3
        assert not sent[-1][1][0][1].flags & wire.SET_SHORT
        for k in range(4):
            add(k, 4)
        assert names() == ["a", "b", "c", "d"] and not sent[-1][1][0][1].flags
        # camera a's next frame closes the open set it is in
        before = len(sent)
        add(0, 5)
        add(0, 6)
        assert len(sent) == before + 1 and names() == ["a"]
        assert sent[-1][1][0][1].index == 5
        # d silent past STALE_NS: sets no longer wait for it
        time.sleep(STALE_NS * 1e-9 + 0.02)
        for g in (7, 8, 9):
            for k in (0, 1, 2):
                add(k, g)
        assert names() == ["a", "b", "c"] and sent[-1][1][0][1].index == 9
        assert not sent[-1][1][0][1].flags & wire.SET_SHORT
    finally:
        sets.close()
        sets.timer.join(1.0)
    assert not sets.timer.is_alive()


def test_a_simulated_node_serves_its_cameras_from_one_thread_on_time():
    """SimNodeCapture: every camera's frames, trigger after trigger, none before it is
    due (taken + the camera's transfer delay) and late by little; a camera that
    disconnects (simulated) is reopened, its frames counting from 0 again."""
    from daemon.config.mocapd import SimConfig
    from daemon.synthetic.node_sim import SimNodeCapture
    from daemon.synthetic.scene import SimCamera, SimScene

    scene = SimScene(SimConfig(cameras=4, drop_camera="cam1", drop_from_s=0.5,
                               drop_for_s=0.1), n_frames=480)  # cam1 opens after 0.3 s
    t0 = time.monotonic_ns()
    got = [[] for _ in range(4)]
    cams = [SimCamera(scene, c, t0) for c in range(4)]
    group = SimNodeCapture(cams, [got[c].append for c in range(4)], retry_s=0.05)
    group.start()

    def cam1_back():  # cam1's frames passed 0.7 s after its own first one
        first = scene.first_trigger.get(1)
        return got[1] and first is not None \
            and scene.trigger_of(got[1][-1]) - first > 0.7 * scene.fps
    deadline = time.monotonic() + 60  # however long a loaded machine takes
    while not cam1_back() and time.monotonic() < deadline:
        time.sleep(0.05)
    group.stop()
    group.join(1.0)
    assert not group.thread.is_alive()
    for c in range(4):
        assert len(got[c]) > 60, c
        late = np.array([s.arrival_ns - scene.taken_ns(s) - scene.transfer_ns[c]
                         for s in got[c]])
        # never early; how late is the machine's (a median of 1.46 ms at load 15): bounded
        # here only to catch a frame held for a period, the figure is bench_nodes.py's
        assert late.min() >= 0 and np.median(late) < 20_000_000, (c, np.median(late))
        triggers = np.array([scene.trigger_of(s) for s in got[c]])
        steps = np.diff(triggers)
        if c != 1:
            assert np.all(steps == 1) and group.states[c].failures == 0
    # cam1 was away 0.5-0.6 s after its first frame: reopened, its frame ids from 0 again
    assert group.states[1].failures >= 1 and group.states[1].connected  # each failed open
    ids = [s.device_frame_id for s in got[1]]
    assert ids.count(0) == 2
    t = (np.array([scene.trigger_of(s) for s in got[1]]) - scene.first_trigger[1]) / scene.fps
    assert not np.any((t >= 0.5) & (t < 0.6)) and t.min() < 0.5 and t.max() > 0.65


def test_clock_and_pose_messages_round_trip():
    assert wire.decode_ping(wire.encode_ping(5, 123)) == (5, 123)
    assert wire.decode_pong(wire.encode_pong(9, 5, 1, 2, 3)) == (9, 5, 1, 2, 3)
    p = wire.decode_pose(wire.encode_pose(3, 77, 10**12, 1500, True, 4, (1.0, 2.0, 0.5),
                                          (0.0, 0.0, 0.6, 0.8), 0.0004))
    assert p["id"] == 3 and p["frame"] == 77 and p["valid"] and p["markers"] == 4
    np.testing.assert_allclose(p["position"], (1.0, 2.0, 0.5))
    np.testing.assert_allclose(p["quaternion"], (0, 0, 0.6, 0.8), atol=1e-7)
    with pytest.raises(wire.WireError):
        wire.decode_pong(b"short")


# ---- the clock estimate ------------------------------------------------------------------------

def _exchanges(clock, seconds, offset_ns, drift_ppm, delay_ns, jitter_ns, seed=0,
               queue_ns=0, queue_p=0.0):
    """Feed `clock` ping exchanges at 20 Hz over a link of delay +- jitter each way (and now
    and then a queue on one leg); returns the truth node(t) = t + offset + drift * t."""
    rng = np.random.default_rng(seed)

    def node(t):
        return t + offset_ns + round(drift_ppm * 1e-6 * t)

    t = 10**9
    for _ in range(int(seconds * 20)):
        d1, d2 = delay_ns + rng.uniform(-jitter_ns, jitter_ns, 2)
        if rng.random() < queue_p:  # a queue on one leg only: an asymmetric exchange
            d1 += rng.uniform(0, queue_ns)
        t1 = t
        t2 = node(t1 + round(d1))
        t3 = t2 + 30_000  # the node's own turnaround
        t4 = t1 + round(d1) + 30_000 + round(d2)
        clock.add(t1, t2, t3, t4)
        t += 50_000_000
    return node, t


def test_clock_offset_within_50_us_over_a_jittery_link_and_follows_50_ppm():
    """1 ms +- 0.2 ms each way, a node 50 ppm fast and 3.7 s ahead, one exchange in five
    queued up to 2 ms on one leg: the estimate at the latest exchange (and mapped times)
    within 50 us of the truth, the drift within 5 ppm."""
    clock = NodeClock()
    node, t = _exchanges(clock, 30, 3_700_000_000, 50.0, 1_000_000, 200_000, seed=3,
                         queue_ns=2_000_000, queue_p=0.2)
    true_offset = node(t) - t
    assert abs(clock.offset_ns(t) - true_offset) < 50_000
    assert abs(clock.status()["drift_ppm"] - 50.0) < 5.0
    assert abs(clock.to_daemon(node(t)) - t) < 50_000


def test_clock_is_not_ready_before_enough_exchanges():
    clock = NodeClock()
    _exchanges(clock, 0.2, 0, 0.0, 100_000, 10_000)  # 4 exchanges
    assert not clock.ready and clock.status()["offset_ms"] is None


# ---- configuration -----------------------------------------------------------------------------

def test_zenoh_settings_are_checked_with_one_line_errors(tmp_path):
    with pytest.raises(UserError, match="zenoh.listen: expected a Zenoh endpoint"):
        parse_config({"zenoh": {"listen": ["127.0.0.1:7447"]}}, tmp_path / "m.toml")
    with pytest.raises(UserError, match="zenoh.cameras: must be one of"):
        parse_config({"zenoh": {"cameras": "all"}})
    with pytest.raises(UserError, match="name: node name 'a/b' cannot go into a Zenoh key"):
        parse_node_config({"name": "a/b"})
    with pytest.raises(UserError, match="publish: must be one of cameras, sets; got 'frames'"):
        parse_node_config({"publish": "frames"})
    with pytest.raises(UserError, match="set_wait_ms: must be between 0.0 and 1000.0"):
        parse_node_config({"set_wait_ms": -1})
    assert parse_node_config({}).publish == "sets"
    cfg = parse_config({"camera": [{"name": "cam0", "source": "zenoh:left"}]})
    assert cfg.zenoh is not None and cfg.zenoh.session.listen == ("tcp/0.0.0.0:7447",)
    assert parse_camera_list("0-2,cam5", [f"cam{i}" for i in range(8)]) == (
        "cam0", "cam1", "cam2", "cam5")
    with pytest.raises(ValueError, match="the rig has cameras 0-7"):
        parse_camera_list("6-9", [f"cam{i}" for i in range(8)])


def test_node_with_a_bad_endpoint_exits_with_one_line():
    r = subprocess.run([sys.executable, "-m", "daemon.cli", "node", "--sim", "--connect",
                        "127.0.0.1:7447"], cwd=ROOT, capture_output=True, text=True,
                       timeout=60, env=dict(os.environ, PYTHONPATH=str(ROOT)))
    assert r.returncode != 0
    assert "expected a Zenoh endpoint" in r.stderr and "Traceback" not in r.stderr
    r = subprocess.run([sys.executable, "-m", "daemon.cli", "node", "--sim", "--publish",
                        "frames"], cwd=ROOT, capture_output=True, text=True,
                       timeout=60, env=dict(os.environ, PYTHONPATH=str(ROOT)))
    assert r.returncode != 0 and "Traceback" not in r.stderr
    assert "--publish must be one of cameras, sets, got 'frames'" in r.stderr


# ---- nodes as processes ------------------------------------------------------------------------

def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def start_node(name, rig, endpoint, cameras, offset_ms=0.0, drift_ppm=0.0, n_cameras=8,
               seconds=60, extra=()):
    return subprocess.Popen(
        [sys.executable, "-m", "daemon.cli", "node", "--sim", "--sim-cameras",
         str(n_cameras), "--cameras", cameras, "--name", name, "--rig", rig, "--connect",
         endpoint, "--clock-offset-ms", str(offset_ms), "--clock-drift-ppm", str(drift_ppm),
         "--duration", str(seconds), *extra],
        cwd=ROOT, env=dict(os.environ, PYTHONPATH=str(ROOT)), stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE, text=True)


def true_offset_ns(offset_ms, drift_ppm, t_ns):
    """What `mocapd node --sim` clocks read minus the machine's, at machine time t_ns."""
    return round(t_ns * (1 + drift_ppm * 1e-6)) + round(offset_ms * 1e6) - t_ns


class DaemonThread:
    """A daemon with [sim] and its cameras served by nodes, run on a thread of the test."""

    def __init__(self, tmp_path, port, rig, seconds, n_cameras=8, extra=None):
        from daemon.service.daemon import Daemon

        data = {"runtime_dir": str(tmp_path / "run"),
                "sim": {"cameras": n_cameras},
                "zenoh": {"rig": rig, "listen": [f"tcp/127.0.0.1:{port}"],
                          "cameras": "announced"}}
        data.update(extra or {})
        self.daemon = Daemon(parse_config(data))
        self.figures = {}
        self.thread = threading.Thread(
            target=lambda: self.figures.update(self.daemon.run(duration_s=seconds)),
            daemon=True)

    def start(self):
        self.thread.start()
        return self

    def wait_for(self, what, timeout_s=30.0):
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            if getattr(self.daemon, "hub", None) is not None and what(self.daemon):
                return True
            time.sleep(0.05)
        return False


def stop(procs):
    for p in procs:
        if p.poll() is None:
            p.send_signal(signal.SIGTERM)
    for p in procs:
        try:
            p.wait(10)
        except subprocess.TimeoutExpired:
            p.kill()


def cameras_live(d, names) -> bool:
    caps = {c.name: c for c in getattr(d, "captures", [])}
    return bool(caps) and all(caps[n].connected for n in names)


def test_two_nodes_feed_one_daemon_clocks_estimated_and_bodies_tracked(tmp_path):
    """Two node processes serve four cameras each, their clocks 12.5 ms ahead and 50 ppm
    fast, and 7 ms behind and 30 ppm slow, one publishing sets and the other single
    frames; the daemon pairs their frames into full sets,
    tracks the scene's bodies as well as with local cameras, and its estimate of each
    node's clock is within 0.5 ms of the truth on loopback (a fraction of the offsets; the
    hop and round-trip times are speeds, measured by benchmarks/bench_nodes.py)."""
    port, rig = free_port(), "two"
    ep = f"tcp/127.0.0.1:{port}"
    d = DaemonThread(tmp_path, port, rig, 120.0).start()  # stopped once checked
    nodes = [start_node("a", rig, ep, "0-3", 12.5, 50.0, seconds=120,
                        extra=("--publish", "sets")),  # a set per trigger
             start_node("b", rig, ep, "4-7", -7.0, -30.0, seconds=120,
                        extra=("--publish", "cameras"))]  # a frame a message
    truth = {"a": (12.5, 50.0), "b": (-7.0, -30.0)}
    try:
        names = [f"cam{i}" for i in range(8)]
        assert d.wait_for(lambda dm: cameras_live(dm, names), 90), "the cameras never came"
        # 2 s of exchanges at 20 Hz per node, however long a loaded machine takes to them
        assert d.wait_for(lambda dm: len(dm.hub.nodes) == 2 and all(
            n.clock.status()["exchanges"] >= 40 for n in dm.hub.nodes.values()), 60), \
            "the nodes' clocks were never estimated"
        errors = {}
        for node in d.daemon.hub.nodes.values():
            t = time.monotonic_ns()
            errors[node.name] = node.clock.offset_ns(t) - true_offset_ns(*truth[node.name], t)
        # tracked for a while longer: 1000 frame sets (about 4 s at 240 fps) from the nodes
        first = d.daemon.mux.last_index
        assert d.wait_for(lambda dm: dm.mux.last_index > first + 1000, 120)
        d.daemon.stop_event.set()
        d.thread.join(30)
    finally:
        stop(nodes)
    assert set(errors) == {"a", "b"}
    # 6 us median on a quiet machine (bench_nodes.py); 0.65 ms once at load 20, the round
    # trips' asymmetry: 2 ms is still a ten-thousandth of the offsets a wrong read leaves
    assert all(abs(e) < 2_000_000 for e in errors.values()), errors
    fig = d.figures
    truth_fig = fig["truth"]
    assert truth_fig["valid_poses"] > 0
    for name, b in truth_fig["bodies"].items():
        assert b["valid_fraction"] > 0.8, (name, b)
        assert b["position_error_mm_rms_without_gross"] < 2.0, (name, b)
    mux = fig["multiplexer"]
    # the two nodes' frames are paired across their clocks: with the clocks mapped wrongly
    # (by more than the pairing tolerance) nearly every set would miss one node's cameras.
    # How many sets a loaded machine completes in time is bench_nodes.py's figure, not this
    # test's (at load 3 beside the test suite, 26-35 % missed a camera, before and after
    # the batched path alike)
    assert mux["incomplete_sets"] < 0.5 * fig["frames"], mux
    nodes_st = {n["name"]: n for n in fig["nodes"]}
    assert nodes_st["a"]["cameras"] == names[:4] and nodes_st["b"]["cameras"] == names[4:]
    for name, (off, drift) in truth.items():
        st = nodes_st[name]
        want = true_offset_ns(off, drift, st["offset_at_ns"]) * 1e-6
        assert abs(st["offset_ms"] - want) < 0.5, (name, st)
        assert st["rtt_ms"] > 0 and st["hop_median_ms"] > 0


def test_a_killed_node_is_dropped_and_its_cameras_rejoin_within_2_s_of_its_restart(
        tmp_path):
    """Node b is killed (SIGKILL) mid-run: its cameras are reported disconnected, node a's
    go on; b started again comes back with a new boot id, counted as a restart, and its
    cameras are in the frame sets again within 2 s of its first message."""
    port, rig = free_port(), "kill"
    ep = f"tcp/127.0.0.1:{port}"
    d = DaemonThread(tmp_path, port, rig, 30.0).start()
    a = start_node("a", rig, ep, "0-3", 1.0, 20.0, seconds=60)
    b = start_node("b", rig, ep, "4-7", -2.0, -20.0, seconds=60)
    b2 = None
    try:
        names = [f"cam{i}" for i in range(8)]
        assert d.wait_for(lambda dm: cameras_live(dm, names), 90), "the cameras never came"
        time.sleep(1.0)
        b.kill()
        b.wait(10)
        # how soon is the machine's (bench_nodes.py): waited for with deadlines a loaded
        # machine meets, in counts of frames and sets, not seconds
        assert d.wait_for(lambda dm: not any(cameras_live(dm, [n]) for n in names[4:]),
                          10.0), "node b's cameras were not dropped"
        frames_a = {c.name: c.frames for c in d.daemon.captures}
        mux = d.daemon.mux
        sets_before = mux.last_index
        assert d.wait_for(lambda dm: all(c.frames > frames_a[c.name] + 150
                                         for c in dm.captures if c.name in names[:4]),
                          30.0), "node a's cameras stalled"
        assert d.wait_for(lambda dm: dm.mux.last_index > sets_before + 150, 30.0), \
            "the frame loop stalled"
        old = {n.boot for n in d.daemon.hub.nodes.values() if n.name == "b"}
        assert d.wait_for(lambda dm: not {n["name"]: n for n in dm.hub.status()}["b"]["alive"],
                          10.0), "node b was not reported gone"
        b2 = start_node("b", rig, ep, "4-7", -2.0, -20.0, seconds=60)
        assert d.wait_for(lambda dm: any(n.name == "b" and n.boot not in old
                                         for n in dm.hub.nodes.values()), 30)
        first = time.monotonic()
        assert d.wait_for(lambda dm: cameras_live(dm, names[4:]), 10.0)
        back = time.monotonic()
        assert back - first < 2.0, f"node b's cameras back {back - first:.2f} s after it"
        # and in the frame sets: in at least half of the next 240. A node that did not
        # rejoin misses them all; beside two CPU hogs the restarted node, still warming up,
        # missed 25-32 % (its process competes with the suite's for the two cores)
        time.sleep(0.2)
        m1, i1 = mux.missing[4:].copy(), mux.last_index
        assert d.wait_for(lambda dm: dm.mux.last_index > i1 + 240, 30.0), "the sets stalled"
        sets = mux.last_index - i1
        assert np.all(mux.missing[4:] - m1 <= 0.5 * sets), (sets, m1, mux.missing[4:])
        st = {n["name"]: n for n in d.daemon.hub.status()}
        assert st["b"]["restarts"] == 1
        d.daemon.stop_event.set()
        d.thread.join(30)
    finally:
        stop([p for p in (a, b, b2) if p is not None])
    failures = {c["name"]: c["failures"] for c in d.figures["cameras"]}
    assert all(failures[n] >= 1 for n in names[4:]), failures


def test_poses_go_out_over_zenoh_to_a_subscriber_on_another_session(tmp_path):
    """A consumer with its own Zenoh session, connected to the daemon, gets every body's
    pose on mocap/<rig>/bodies/<name>, matching what the daemon tracked."""
    from daemon.publish.zenoh_session import ZenohSettings

    port, rig = free_port(), "poses"
    ep = f"tcp/127.0.0.1:{port}"
    d = DaemonThread(tmp_path, port, rig, 120.0).start()  # stopped once checked
    node = start_node("a", rig, ep, "0-7", 0.0, 0.0, seconds=120)
    got = {}
    session = None
    try:
        assert d.wait_for(lambda dm: cameras_live(dm, [f"cam{i}" for i in range(8)]))
        session = ZenohSettings(rig, (), (ep,)).open()

        def on_pose(sample):
            got.setdefault(str(sample.key_expr), []).append(
                wire.decode_pose(sample.payload.to_bytes()))

        sub = session.declare_subscriber(f"mocap/{rig}/bodies/*", on_pose)
        end = time.monotonic() + 60
        while time.monotonic() < end and not (
                len(got) == 3 and all(len(m) > 300 for m in list(got.values()))):
            time.sleep(0.05)
        sub.undeclare()
        shown = subprocess.run([sys.executable, "-m", "daemon.cli", "status", "--runtime-dir",
                                str(tmp_path / "run")], cwd=ROOT, capture_output=True,
                               text=True, timeout=60, env=dict(os.environ,
                                                               PYTHONPATH=str(ROOT)))
        d.daemon.stop_event.set()
        d.thread.join(30)
    finally:
        if session is not None:
            session.close()
        stop([node])
    # `mocapd status` lists the node: alive, its 8 cameras, its clock
    row = [ln.split() for ln in shown.stdout.splitlines() if ln.split()[:1] == ["a"]]
    assert "drift ppm" in shown.stdout and row and row[0][1:3] == ["yes", "8"], shown.stdout
    keys = sorted(got)
    assert keys == [f"mocap/{rig}/bodies/body{i}" for i in range(3)], keys
    for msgs in got.values():
        valid = [m for m in msgs if m["valid"]]
        # valid in 0.9-1.0 of them on a quiet machine, 0.72 at load 11 (sets short of a
        # camera while the node and the daemon wait for a core): the share is a machine's
        # figure (bench_nodes.py); here, that valid poses go out in numbers
        assert len(valid) > 100 and len(msgs) > 300
        q = np.array([m["quaternion"] for m in valid])
        np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-5)
        assert all(m["markers"] >= 3 for m in valid)
    out = {o["name"]: o for o in d.figures["outputs"]}
    assert out[f"zenoh:mocap/{rig}/bodies"]["sent"] > 300


def test_a_node_serving_a_camera_the_daemon_does_not_take_is_warned_about(tmp_path, caplog):
    """A node announcing a camera outside the daemon's rig gets one warning naming it."""
    import logging

    from daemon.config.zenoh import DaemonZenoh
    from daemon.nodes.remote import NodeHub
    from daemon.publish.zenoh_session import ZenohSettings

    port = free_port()
    hub = NodeHub(DaemonZenoh(ZenohSettings("warn", (f"tcp/127.0.0.1:{port}",), ())),
                  ["cam0", "cam1"], {"cam0": "cam0", "cam1": "cam1"})
    hub.start()
    node = start_node("x", "warn", f"tcp/127.0.0.1:{port}", "cam1,cam5", n_cameras=8,
                      seconds=30)
    try:
        with caplog.at_level(logging.WARNING, logger="mocapd.nodes"):
            end = time.monotonic() + 60
            while time.monotonic() < end and "cam5" not in caplog.text:
                time.sleep(0.1)
            time.sleep(1.5)  # a second announcement: still one warning
    finally:
        stop([node])
        hub.close()
    warned = [r for r in caplog.records if "cam5" in r.getMessage()]
    assert len(warned) == 1 and "node x serves camera cam5" in warned[0].getMessage()
    assert hub.unknown > 0  # its blobs were heard and left aside
    assert not any("cam1" in r.getMessage() for r in caplog.records)
