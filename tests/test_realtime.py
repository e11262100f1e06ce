"""Real-time scheduling of the live daemon (daemon/process/realtime.py) and the latency stage
figures that showed why it is needed."""

from __future__ import annotations

import json
import logging
import os
import threading

import pytest

from daemon.config.mocapd import load_config
from daemon.process.realtime import current_policy, raise_priority, restore_normal

may_be_realtime = pytest.mark.skipif(
    os.geteuid() != 0, reason="real-time scheduling needs root or CAP_SYS_NICE; the "
                              "refused case is tested below")


def _in_thread(fn):
    """Run fn on a thread of its own (scheduling is per thread: never change pytest's)."""
    out = {}
    t = threading.Thread(target=lambda: out.update(value=fn()))
    t.start()
    t.join(10)
    return out["value"]


@may_be_realtime
def test_threads_started_afterwards_inherit_it():
    def body():
        said = raise_priority(10)
        mine = current_policy()
        child = {}
        t = threading.Thread(target=lambda: child.update(policy=current_policy()))
        t.start()
        t.join()
        restore_normal()
        return said, mine, child["policy"], current_policy()

    said, mine, thread_policy, after = _in_thread(body)
    assert said == "SCHED_RR 10"
    assert mine == "SCHED_RR" and thread_policy == "SCHED_RR"
    assert after == "SCHED_OTHER"
    assert current_policy() == "SCHED_OTHER"  # pytest's own thread was never touched


def test_a_refused_priority_is_one_warning_with_the_remedy(monkeypatch, caplog):
    def refuse(*_):
        raise PermissionError(1, "Operation not permitted")

    monkeypatch.setattr(os, "sched_setscheduler", refuse)
    with caplog.at_level(logging.WARNING, logger="mocapd.realtime"):
        said = raise_priority(10)
    assert said == "normal (SCHED_RR 10 refused)"
    assert len(caplog.records) == 1
    assert "LimitRTPRIO=10" in caplog.text and "realtime_priority = 0" in caplog.text


def test_priority_zero_leaves_scheduling_alone():
    assert _in_thread(lambda: (raise_priority(0), current_policy())) == (
        "normal (real-time scheduling not asked for: --realtime)", "SCHED_OTHER")


def test_the_configuration_key_and_the_flag(tmp_path, start_refused):
    """Real-time scheduling only where it is asked for: a file's priority or --realtime
    (which the system unit passes); a run in a terminal or --sim stays normal."""
    from daemon.commands.start_run import REALTIME_DEFAULT, StartOverrides

    good = tmp_path / "good.toml"
    good.write_text("[pipeline]\nrealtime_priority = 20\n")
    assert load_config(good).realtime_priority == 20
    assert load_config(None).realtime_priority == 0
    assert StartOverrides(sim=True).apply(load_config(None)).realtime_priority == 0
    assert StartOverrides(realtime=True).apply(load_config(None)).realtime_priority == \
        REALTIME_DEFAULT
    assert StartOverrides(realtime=True).apply(load_config(good)).realtime_priority == 20
    bad = tmp_path / "bad.toml"
    bad.write_text("[pipeline]\nrealtime_priority = 100\n")
    assert "pipeline.realtime_priority: must be between 0 and 99, got 100" in start_refused(bad)


@may_be_realtime
def test_a_live_run_tracks_real_time_reports_its_stages_and_returns_normal(tmp_path,
                                                                          mocapd_cli):
    out = tmp_path / "fig.json"
    r = mocapd_cli("start", "--sim", "--duration", 2.5, "--sim-fps", 120, "--json", out,
                   "--runtime-dir", tmp_path / "rt", "--udp", "127.0.0.1:9", "--realtime")
    assert r.code == 0, r.err
    fig = json.loads(out.read_text())
    assert fig["scheduling"] == "SCHED_RR 10"
    assert current_policy() == "SCHED_OTHER"  # the in-process run put its caller back
    st = fig["latency_stages"]
    assert set(st) == {"total", "delivery", "pickup", "compute", "outputs"}
    parts = sum(st[k]["median_ms"] for k in ("delivery", "pickup", "compute", "outputs"))
    # medians of the parts need not add up exactly, but they bracket the whole
    assert 0.5 * st["total"]["median_ms"] <= parts <= 2.0 * st["total"]["median_ms"]
    assert 0 < st["compute"]["median_ms"] < st["total"]["median_ms"]
    # the simulated cameras deliver 0.1-0.5 ms after capture: never sooner (a loaded
    # machine's threads may deliver much later, so no upper bound but a sane one)
    assert 0.1 <= st["delivery"]["median_ms"] <= 1000


def test_a_live_run_keeps_blas_on_its_calling_thread_and_gives_the_limit_back(tmp_path,
                                                                              mocapd_cli):
    """OpenBLAS's worker threads start with numpy, at normal priority: a real-time thread
    waiting for them would wait behind every other process. While the daemon runs, BLAS
    uses one thread; afterwards the caller's limit is back."""
    from threadpoolctl import threadpool_info

    def blas_threads():
        return {lib["internal_api"]: lib["num_threads"] for lib in threadpool_info()
                if lib["user_api"] == "blas"}

    before = blas_threads()
    assert before, "numpy's BLAS is not seen by threadpoolctl"
    seen, stop = [], threading.Event()

    def watch():
        while not stop.is_set():
            seen.append(blas_threads())
            stop.wait(0.05)

    w = threading.Thread(target=watch)
    w.start()
    try:
        # at normal priority: the limit holds for any run (a test starts no real-time
        # process it does not need)
        r = mocapd_cli("start", "--sim", "--duration", 2.0, "--sim-fps", 60,
                       "--runtime-dir", tmp_path / "rt", "--udp", "127.0.0.1:9")
    finally:
        stop.set()
        w.join(10)
    assert r.code == 0, r.err
    assert any(set(s.values()) == {1} for s in seen)
    assert blas_threads() == before


def test_a_notify_socket_nobody_reads_never_blocks_the_frame_loop(tmp_path, monkeypatch):
    """sd_notify runs on the frame loop every second: when the manager stops reading and
    the socket's queue fills, the message is dropped, not waited for."""
    import socket
    import time

    from daemon.process.notify import sd_notify

    path = tmp_path / "notify"
    rx = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    rx.bind(str(path))
    monkeypatch.setenv("NOTIFY_SOCKET", str(path))
    try:
        started = time.monotonic()
        sent = [sd_notify(f"STATUS={i} fps" + "x" * 200) for i in range(2000)]
        took = time.monotonic() - started
    finally:
        rx.close()
    assert sent[0] and not sent[-1]  # the first went, the queue filled and later ones dropped
    assert took < 60.0  # a blocking send would hang here for good


def test_a_live_run_keeps_its_start_up_out_of_the_collector_and_gives_it_back(tmp_path):
    """While a live daemon tracks, what it built to start (scene, rig, trackers, modules)
    is frozen out of the cycle collector's full passes (daemon/process/heap.py), and an
    in-process run gives it back when it ends."""
    import gc

    from daemon.config.mocapd import parse_config
    from daemon.service.daemon import Daemon

    assert gc.get_freeze_count() == 0
    frozen = []
    d = Daemon(parse_config({"runtime_dir": str(tmp_path / "run"), "sim": {"cameras": 4},
                             "pipeline": {"realtime_priority": 0}}))
    # 20 frames however long a loaded machine takes (the bound only ends a run that hangs)
    d.run(frames=20, duration_s=300.0,
          progress=lambda _frames: frozen.append(gc.get_freeze_count()))
    assert len(frozen) > 5  # it tracked
    assert min(frozen) > 50_000, min(frozen)  # what starting up made: kept aside
    assert gc.get_freeze_count() == 0



_NODE_PRIORITIES = """
import json, os, sys, threading, time
from daemon.nodes.node import Node, NodeTime
from daemon.nodes.settings import NodeConfig
from daemon.publish.zenoh_session import ZenohSettings

endpoint = sys.argv[1]
seen = {}


class Runner:
    def __init__(self):
        self.stop_event = threading.Event()
        self.thread = threading.Thread(target=self._run)

    def _run(self):
        seen["capture"] = os.sched_getparam(0).sched_priority
        self.stop_event.wait(30)

    def start(self):
        self.thread.start()

    def stop(self):
        self.stop_event.set()

    def join(self, timeout):
        self.thread.join(timeout)


class State:
    connected, frames = True, 0


def body():
    cfg = NodeConfig(name="rt", session=ZenohSettings(rig="rt", listen=(endpoint,)),
                     realtime_priority=5, publish="sets")
    node = Node(cfg, [], NodeTime(), capture=lambda sources, pushes: ([Runner()], [State()]))
    node.start()
    peer = ZenohSettings(rig="rt", connect=(endpoint,)).open()  # a link: its rx/tx threads
    deadline = time.monotonic() + 30
    names = lambda: {open(f"/proc/self/task/{t}/comm").read().strip()
                     for t in os.listdir("/proc/self/task")}
    while time.monotonic() < deadline and not ("capture" in seen and "rx-0" in names()):
        time.sleep(0.05)
    threads = {}
    for tid in os.listdir("/proc/self/task"):
        name = open(f"/proc/self/task/{tid}/comm").read().strip()
        threads.setdefault(name, []).append(os.sched_getparam(int(tid)).sched_priority)
    seen.update(scheduling=node.scheduling, threads=threads,
                comm=open("/proc/self/comm").read().strip())  # python, python3, ...
    peer.close()
    node.close()


t = threading.Thread(target=body)
t.start()
t.join()
print(json.dumps(seen))
"""


@may_be_realtime
def test_a_node_runs_its_network_a_step_above_its_capture_threads():
    """A ready set must leave while other cameras' detection holds the cores: Zenoh's
    threads, the clock's answers and the set timer at the node's priority + 1, its capture
    threads at it. In a process of its own: Zenoh starts its threads once per process."""
    import socket
    import subprocess
    import sys

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    out = subprocess.run([sys.executable, "-c", _NODE_PRIORITIES, f"tcp/127.0.0.1:{port}"],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    seen = json.loads(out.stdout.strip().splitlines()[-1])
    assert seen["scheduling"] == "SCHED_RR 5 (network 6)"
    assert seen["capture"] == 5
    threads = seen["threads"]
    network = [p for name, ps in threads.items() if name.startswith(("rx-", "tx-", "net-"))
               for p in ps]
    assert network and set(network) == {6}, threads
    # Python's own threads carry the interpreter's name here (python, python3): the set
    # timer and the clock's answers are the two at 6; the thread that started the node and
    # its capture thread are at 5
    python = sorted(p for p in threads[seen["comm"]] if p > 0)
    assert python.count(6) >= 2 and python.count(5) == 2 and set(python) == {5, 6}, threads
