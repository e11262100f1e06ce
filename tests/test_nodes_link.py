"""The node clock estimate over a link that is not loopback: 1 ms +- 0.2 ms each way.

On loopback a round trip takes a fraction of a millisecond and any estimate looks good.
Here the node reaches the daemon through a delaying link: the kernel's netem between two
network namespaces where the kernel has it, else daemon.synthetic.link (a TCP relay that
holds each direction's bytes 1 ms +- 0.2 ms) on loopback or inside a namespace. The node's
clock runs 50 ppm fast, seconds ahead of the machine's; the estimate is scored against
that truth. No traffic leaves loopback or the namespaces made here.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from test_nodes import (
    ROOT,
    DaemonThread,
    cameras_live,
    free_port,
    start_node,
    stop,
    true_offset_ns,
)

from daemon.nodes.clock import WINDOW

OFFSET_MS, DRIFT_PPM = 3700.0, 50.0
# The clock estimate is timed by the processes' own wake-ups, so on a machine busy with
# other work it is off by more than on a rig: these tests run daemon and node at normal
# priority (a test starts a real-time process only when real time is what it tests:
# tests/test_realtime.py) and bound the error at a fifth of the link's 1 ms delay, which
# an estimate that mistook the delay for offset would exceed; the 50 us target is
# measured by benchmarks/bench_nodes.py.
OFFSET_ERROR_US = (200.0, 1000.0)  # median, worst of the samples
# median, worst: the node's clock runs 50 ppm fast, so an estimate that ignored drift
# would be 50 off; a fifth and a half of that (beside two CPU hogs the median was 5.7)
DRIFT_ERROR_PPM = (10.0, 25.0)
ENV = dict(os.environ, PYTHONPATH=str(ROOT))
# Daemons, nodes and links run until a test has what it needs and stops them; the waits
# are generous (a machine at load 30 took over 90 s to bring a node's cameras up).
LONG_S, WAIT_S = 600, 240
# The two clock tests last as long as the estimate's window takes to fill (WINDOW exchanges
# at 20 Hz), whatever the cameras' rate: at 120 fps instead of the sim's 240 the daemon and
# node spend about half the CPU over the same 20-odd seconds. The clock exchanges, the
# samples scored and the bounds are the same (the 1000 frames the namespace test waits for
# still come well inside the window's fill).
FPS = 120.0


def start_link(listen, to, netns=None, seconds=LONG_S, delay_ms=1.0, jitter_ms=0.2):
    cmd = [sys.executable, "-m", "daemon.synthetic.link", "--listen", listen, "--to", to,
           "--delay-ms", str(delay_ms), "--jitter-ms", str(jitter_ms), "--seconds",
           str(seconds)]
    if netns:
        cmd = ["ip", "netns", "exec", netns, *cmd]
    return subprocess.Popen(cmd, cwd=ROOT, env=ENV, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)


def test_clock_offset_within_50_us_over_a_1_ms_jittery_link_and_50_ppm_followed(tmp_path):
    """One node through the delaying link on loopback: once the estimate's window is full
    (20 s of exchanges), the daemon's offset estimate is within OFFSET_ERROR_US of the
    truth (the median of half-second samples, and the worst) and its drift within
    DRIFT_ERROR_PPM of 50 ppm."""
    port, link_port, rig = free_port(), free_port(), "link"
    d = DaemonThread(tmp_path, port, rig, LONG_S, n_cameras=4,
                     extra={"sim": {"cameras": 4, "fps": FPS}}).start()
    link = start_link(f"127.0.0.1:{link_port}", f"127.0.0.1:{port}", seconds=LONG_S)
    node = start_node("far", rig, f"tcp/127.0.0.1:{link_port}", "0-3", OFFSET_MS, DRIFT_PPM,
                      n_cameras=4, seconds=LONG_S, extra=("--sim-fps", str(FPS)))
    errors, drifts, rtts = [], [], []
    try:
        assert d.wait_for(lambda dm: cameras_live(dm, [f"cam{i}" for i in range(4)]), WAIT_S)
        assert d.wait_for(lambda dm: all(n.clock.status()["exchanges"] >= WINDOW
                                         for n in dm.hub.nodes.values()), WAIT_S)
        for _ in range(12):
            (n,) = d.daemon.hub.nodes.values()
            t = time.monotonic_ns()
            errors.append(n.clock.offset_ns(t) - true_offset_ns(OFFSET_MS, DRIFT_PPM, t))
            st = n.clock.status()
            drifts.append(st["drift_ppm"])
            rtts.append(st["rtt_ms"])
            time.sleep(0.5)
        d.daemon.stop_event.set()
        d.thread.join(30)
    finally:
        stop([node, link])
    err_us = np.abs(errors) * 1e-3
    assert np.median(rtts) > 1.8, "the link did not delay the round trips"
    assert np.median(err_us) <= OFFSET_ERROR_US[0] and err_us.max() <= OFFSET_ERROR_US[1], \
        err_us
    drift_err = np.abs(np.array(drifts) - DRIFT_PPM)
    assert np.median(drift_err) < DRIFT_ERROR_PPM[0] and \
        drift_err.max() < DRIFT_ERROR_PPM[1], drifts
    truth = d.figures["truth"]
    for name, b in truth["bodies"].items():
        assert b["valid_fraction"] > 0.7, (name, b)


def test_a_node_behind_a_slow_link_is_reported_late_and_nothing_else_stalls(tmp_path):
    """Node b reaches the daemon through a link that holds each direction 300 ms: its
    clock is still estimated (the delay is symmetric), but every frame arrives 300 ms
    after b got it, beyond max_lag_ms (100): b is reported behind (late frames, its lag),
    its cameras are left out of the frame sets, and node a's cameras, on loopback, are
    tracked at the full rate."""
    port, link_port, rig = free_port(), free_port(), "slow"
    d = DaemonThread(tmp_path, port, rig, LONG_S).start()
    link = start_link(f"127.0.0.1:{link_port}", f"127.0.0.1:{port}", seconds=LONG_S,
                      delay_ms=300, jitter_ms=0)
    a = start_node("a", rig, f"tcp/127.0.0.1:{port}", "0-3", 5.0, 10.0, seconds=LONG_S)
    b = start_node("b", rig, f"tcp/127.0.0.1:{link_port}", "4-7", -5.0, -10.0,
                   seconds=LONG_S)
    try:
        names = [f"cam{i}" for i in range(8)]
        assert d.wait_for(lambda dm: cameras_live(dm, names[:4]), WAIT_S)
        assert d.wait_for(lambda dm: {n["name"]: n for n in dm.hub.status()}.get("b", {})
                          .get("late", 0) > 200, WAIT_S), "node b's frames never came late"
        # not stalled behind b (a stall: no set at all): 240 more sets come, however long
        # a loaded machine takes to them (a quiet one: 1 s; the rate is a benchmark's)
        i0 = d.daemon.mux.last_index
        went_on = d.wait_for(lambda dm: dm.mux.last_index > i0 + 240, WAIT_S)
        st = {n["name"]: n for n in d.daemon.hub.status()}
        caps = {c.name: c for c in d.daemon.captures}
        d.daemon.stop_event.set()
        d.thread.join(30)
    finally:
        stop([a, b, link])
    assert st["b"]["lag_ms"] > 250 and st["b"]["late"] > 200 and st["b"]["samples"] > 200
    assert st["b"]["rtt_ms"] > 500  # the clock exchanges took the slow link too
    # b's frames all late, a's (loopback) not: most on time even on a machine at load 30,
    # where some go past max_lag_ms while the capture and frame threads wait for a core
    assert st["a"]["late"] < 0.5 * st["a"]["samples"], st["a"]
    assert not any(caps[n].connected for n in names[4:])
    assert all(caps[n].connected for n in names[:4])
    assert went_on, "the frame loop stalled behind node b"


# ---- network namespaces --------------------------------------------------------------------

def _netem_available() -> bool:
    try:
        import gzip

        with gzip.open("/proc/config.gz", "rt") as f:
            config = f.read()
        return "CONFIG_NET_SCH_NETEM=y" in config or "CONFIG_NET_SCH_NETEM=m" in config
    except OSError:
        return Path("/sys/module/sch_netem").exists()


def _why_no_netns() -> str | None:
    if os.geteuid() != 0:
        return "network namespaces need root"
    if shutil.which("ip") is None:
        return "`ip` (iproute2) is not installed"
    r = subprocess.run(["ip", "netns", "add", f"mcd-probe-{os.getpid()}"],
                       capture_output=True, text=True)
    if r.returncode != 0:
        return f"cannot make a network namespace: {r.stderr.strip()}"
    subprocess.run(["ip", "netns", "del", f"mcd-probe-{os.getpid()}"], capture_output=True)
    return None


@pytest.fixture(scope="module")
def namespaces():
    """Two namespaces joined by a veth pair, 10.213.77.1 (daemon) and .2 (node); removed
    afterwards. Addresses exist only inside them."""
    why = _why_no_netns()
    if why:
        pytest.skip(why)
    a, b = f"mcd-d-{os.getpid()}", f"mcd-n-{os.getpid()}"
    va, vb = f"mcdd{os.getpid() % 100000}", f"mcdn{os.getpid() % 100000}"
    steps = [["ip", "netns", "add", a], ["ip", "netns", "add", b],
             ["ip", "link", "add", va, "type", "veth", "peer", "name", vb],
             ["ip", "link", "set", va, "netns", a], ["ip", "link", "set", vb, "netns", b],
             ["ip", "-n", a, "addr", "add", "10.213.77.1/30", "dev", va],
             ["ip", "-n", b, "addr", "add", "10.213.77.2/30", "dev", vb],
             ["ip", "-n", a, "link", "set", va, "up"], ["ip", "-n", b, "link", "set", vb, "up"],
             ["ip", "-n", a, "link", "set", "lo", "up"],
             ["ip", "-n", b, "link", "set", "lo", "up"]]
    try:
        for cmd in steps:
            subprocess.run(cmd, check=True, capture_output=True, text=True)
        yield {"daemon": a, "node": b, "veth": (va, vb)}
    finally:
        for ns in (a, b):  # deleting a namespace deletes its end of the veth, and the pair
            subprocess.run(["ip", "netns", "del", ns], capture_output=True)


class NamespaceRig:
    """A daemon in one namespace and three nodes in the other, 1 ms +- 0.2 ms each way
    between them (netem on the veth where the kernel has it, else the delaying relay inside
    the node's namespace). The daemon listens with a users file: node "good" presents a
    listed user's password and serves cam0-3 with a clock 50 ppm fast and seconds ahead;
    "none" (cam4-5, no credentials) and "wrong" (cam6-7, a wrong password) must be refused.
    One start serves both tests below (the clock and the refusals: each asserts on its own
    nodes), where two took 20 s more; every status a test reads is also kept here, so the
    refusal test sees all the refused nodes' chances to join, from the start."""

    def __init__(self, namespaces, tmp: Path) -> None:
        a, b = namespaces["daemon"], namespaces["node"]
        port = 17000 + os.getpid() % 1000
        self.netem = _netem_available()
        if self.netem:
            for ns, dev in zip((a, b), namespaces["veth"], strict=True):
                subprocess.run(["ip", "netns", "exec", ns, "tc", "qdisc", "add", "dev", dev,
                                "root", "netem", "delay", "1ms", "0.2ms"], check=True)
        self.tmp, self.runtime = tmp, tmp / "run"
        users = tmp / "zenoh-users.txt"
        users.write_text("node-a:correct horse battery\n")
        conf = tmp / "mocapd.toml"
        conf.write_text(f'runtime_dir = "{self.runtime}"\n[sim]\ncameras = 8\nfps = {FPS}\n'
                        f'[zenoh]\nrig = "ns"\nlisten = ["tcp/10.213.77.1:{port}"]\n'
                        f'cameras = "announced"\nusers_file = "{users}"\n')
        self.procs = [subprocess.Popen(
            ["ip", "netns", "exec", a, sys.executable, "-m", "daemon.cli", "start", "--config",
             str(conf), "--duration", str(LONG_S)], cwd=ROOT, env=ENV,
            stdout=subprocess.DEVNULL, stderr=(tmp / "daemon.err").open("w"))]
        direct = endpoint = f"tcp/10.213.77.1:{port}"
        if not self.netem:
            link_port = port + 1
            self.procs.append(start_link(f"127.0.0.1:{link_port}", f"10.213.77.1:{port}",
                                         netns=b))
            endpoint = f"tcp/127.0.0.1:{link_port}"
        listed = 'user = "node-a"\npassword = "correct horse battery"\n'
        for name, cams, creds, to, clock in (
                ("good", "0-3", listed, endpoint,
                 ["--clock-offset-ms", str(OFFSET_MS), "--clock-drift-ppm", str(DRIFT_PPM)]),
                ("none", "4-5", "", direct, []),
                ("wrong", "6-7", 'user = "node-a"\npassword = "guess"\n', direct, [])):
            node_toml = tmp / f"{name}.toml"
            node_toml.write_text(f'name = "{name}"\n[zenoh]\nrig = "ns"\n'
                                 f'connect = ["{to}"]\n{creds}')
            self.procs.append(subprocess.Popen(
                ["ip", "netns", "exec", b, sys.executable, "-m", "daemon.cli", "node",
                 "--config", str(node_toml), "--sim", "--sim-cameras", "8", "--cameras", cams,
                 "--sim-fps", str(FPS), *clock, "--duration", str(LONG_S)], cwd=ROOT, env=ENV,
                stdout=subprocess.DEVNULL, stderr=(tmp / f"{name}.err").open("w")))
        self.seen: set[str] = set()  # cameras with frames in any status read
        self.nodes: set[str] = set()  # nodes any status listed
        self.good_since = None  # when node good's cameras were first seen

    def status(self) -> dict | None:
        """The daemon's status (None while it is not up), its cameras and nodes kept."""
        from daemon.service.control import request

        try:
            st = request(self.runtime, {"cmd": "status"}, timeout_s=2.0)
        except Exception:  # noqa: BLE001 - not up yet
            return None
        self.seen |= {c["name"] for c in st["cameras"] if c.get("frames", 0) > 0}
        self.nodes |= {n["name"] for n in st.get("nodes") or []}
        if {"cam0", "cam1", "cam2", "cam3"} <= self.seen and self.good_since is None:
            self.good_since = time.monotonic()
        return st

    def logs(self) -> dict:
        return {p.name: p.read_text()[-600:] for p in self.tmp.glob("*.err")}


@pytest.fixture(scope="module")
def ns_rig(namespaces, tmp_path_factory):
    rig = NamespaceRig(namespaces, tmp_path_factory.mktemp("ns-rig"))
    try:
        yield rig
    finally:
        stop(rig.procs)


def test_node_in_a_network_namespace_over_a_delayed_link(ns_rig):
    """The daemon in one namespace, node good in another over the 1 ms +- 0.2 ms link: the
    daemon tracks the node's cameras and, once the estimate's window is full, its status
    reports the node's clock within OFFSET_ERROR_US of the truth and its drift within
    DRIFT_ERROR_PPM."""
    errors, drifts, rtts, frames = [], [], [], 0
    end = time.monotonic() + WAIT_S
    while time.monotonic() < end and (len(errors) < 12 or frames < 1000):
        time.sleep(0.5)
        st = ns_rig.status()
        good = [n for n in (st or {}).get("nodes") or [] if n["name"] == "good"]
        if not good or good[0]["clock_exchanges"] < WINDOW:  # the window not full
            continue
        n = good[0]
        frames = st["frames"]  # the node's frames tracked: 1000 waited for
        if len(errors) == 12:
            continue
        want = true_offset_ns(OFFSET_MS, DRIFT_PPM, n["offset_at_ns"]) * 1e-6
        errors.append((n["offset_ms"] - want) * 1e3)
        drifts.append(n["drift_ppm"])
        rtts.append(n["rtt_ms"])
    assert len(errors) == 12, f"the daemon never reported the node's clock: {ns_rig.logs()}"
    assert frames > 1000 and np.median(rtts) > 1.8
    err_us = np.abs(errors)
    assert np.median(err_us) <= OFFSET_ERROR_US[0] and err_us.max() <= OFFSET_ERROR_US[1], \
        err_us
    drift_err = np.abs(np.array(drifts) - DRIFT_PPM)
    assert np.median(drift_err) < DRIFT_ERROR_PPM[0] and \
        drift_err.max() < DRIFT_ERROR_PPM[1], drifts


def test_a_node_without_the_credentials_is_refused_across_namespaces(ns_rig):
    """The daemon listens on the namespaces' network with a users file: the node that
    presents a listed user's password serves its cameras; one without credentials, and one
    with a wrong password, are refused at Zenoh's handshake and their cameras never come,
    though they had 8 s more than the good one took to come (all of the clock test's time,
    when it ran first)."""
    end = time.monotonic() + WAIT_S
    while time.monotonic() < end:
        time.sleep(0.5)
        ns_rig.status()
        if ns_rig.good_since is not None and time.monotonic() - ns_rig.good_since > 8:
            break  # the refused nodes had the same time to join as the good one
    seen, nodes = ns_rig.seen, ns_rig.nodes
    assert {"cam0", "cam1", "cam2", "cam3"} <= seen, \
        f"the node with the credentials never came: {ns_rig.logs()}"
    assert not seen & {"cam4", "cam5", "cam6", "cam7"}, (seen, nodes, ns_rig.logs())
    assert nodes == {"good"}, nodes
