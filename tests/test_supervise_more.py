"""The daemon's long-lived parts outside its own threads, supervised (issue 30): the live
view's process, the Zenoh session and the node-clocks pinger.

Each is broken under a live `mocapd start --sim` run in this process (loopback ports picked
free): the view process is killed, the pinger raises, the Zenoh session is closed under the
daemon. Each must come back (a new view process serving the page and taking frames, pings
going out again, a reopened session carrying poses), with its restarts in `mocapd status
--json` and one log line.
"""

from __future__ import annotations

import json
import logging
import os
import signal
import socket
import threading
import time
import urllib.request
from dataclasses import replace

import pytest

from daemon.config.mocapd import load_config
from daemon.process.supervise import Supervised

DEADLINE_S = 90.0
SIM = "[sim]\ncameras = 3\nbodies = 2\nfps = 60.0\nseed = 11\n"


class Boom(RuntimeError):
    """The injected bug."""


def wait_for(cond, what: str, timeout_s: float = DEADLINE_S) -> None:
    deadline = time.monotonic() + timeout_s
    while not cond():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.05)


def _free_tcp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _thread(status: dict, name: str) -> dict:
    found = [t for t in status["threads"] if t["name"] == name]
    assert len(found) == 1, (name, [t["name"] for t in status["threads"]])
    return found[0]


def _run_daemon(tmp_path, text: str, view: tuple | None = None):
    from daemon.service.daemon import Daemon

    cfg_path = tmp_path / "mocapd.toml"
    cfg_path.write_text(text)
    rt = tmp_path / "rt"
    daemon = Daemon(replace(load_config(cfg_path), runtime_dir=rt),
                    extend=lambda c: replace(c, runtime_dir=rt))
    if view is not None:
        from daemon.view.link import ViewLink

        daemon.view = ViewLink(*view)
    thread = threading.Thread(target=daemon.run, kwargs={"duration_s": 600.0}, daemon=True)
    thread.start()
    wait_for(lambda: getattr(daemon, "pipeline", None) is not None
             and daemon.pipeline.stats.frames >= 20 and thread.is_alive(), "the daemon")
    return daemon, thread, rt


def _stop(daemon, thread) -> None:
    daemon.handle({"cmd": "stop"})
    thread.join(30)
    assert not thread.is_alive()


# ---- the back-off ---------------------------------------------------------------------------

def _failing_loop(n: int, record: list, **kw) -> Supervised:
    """A loop that fails `n` times (recording the wait its supervisor waited before each
    entry), then returns."""
    class Lost(RuntimeError):
        pass

    def loop():
        record.append(sup.next_wait_s())
        if len(record) <= n:
            raise Lost("gone")

    sup = Supervised("w", loop, wait_s=0.001, max_wait_s=0.004, expected=(Lost,), **kw)
    return sup


def test_the_back_off_doubles_to_its_ceiling_and_an_expected_failure_has_no_traceback(caplog):
    waits = []
    sup = _failing_loop(6, waits)
    with caplog.at_level(logging.ERROR, "mocapd"):
        sup.start().join(DEADLINE_S)
    # entry k came after k failures in a row: the wait was 0.001 * 2^(k-1), at most 0.004
    assert waits == [0.001, 0.001, 0.002, 0.004, 0.004, 0.004, 0.004]
    assert sup.status()["restarts"] == 6 and sup.status()["state"] == "stopped"
    lines = [r for r in caplog.records if r.name == "mocapd.supervise"]
    assert len(lines) == 1 and lines[0].exc_info is None
    assert lines[0].getMessage() == "w: thread failed (Lost: gone), restarting it"


def test_a_loop_that_ran_healthy_before_failing_starts_its_back_off_afresh(monkeypatch):
    import daemon.process.supervise as supervise

    monkeypatch.setattr(supervise, "HEALTHY_S", 0.0)  # every run counts as healthy
    waits = []
    _failing_loop(4, waits).start().join(DEADLINE_S)
    assert waits == [0.001] * 5


# ---- the view process ------------------------------------------------------------------------

OPENER = urllib.request.build_opener(urllib.request.ProxyHandler({}))  # no proxy for loopback


def _page(port: int) -> int:
    try:
        with OPENER.open(f"http://127.0.0.1:{port}/", timeout=5) as r:
            return r.status
    except OSError:
        return 0


def test_a_killed_view_process_is_restarted_and_status_says_so(tmp_path, caplog, mocapd_cli):
    port = _free_tcp_port()
    caplog.set_level(logging.WARNING, "mocapd")
    daemon, thread, rt = _run_daemon(tmp_path, SIM, view=("127.0.0.1", port))
    try:
        view = daemon.view
        wait_for(lambda: view.sent > 5 and _page(port) == 200, "the view serving")
        first = view.process.pid
        st = daemon.status()
        assert st["view"]["alive"] and st["view"]["restarts"] == 0
        assert _thread(st, "view-feed")["restarts"] == 0

        os.kill(first, signal.SIGKILL)
        wait_for(lambda: view.restarts == 1 and view.process.is_alive(), "a new view process")
        assert view.process.pid != first and view.last_exit == -signal.SIGKILL
        sent = view.sent
        wait_for(lambda: view.sent > sent + 5 and _page(port) == 200,
                 "the new view serving and taking frames")
        frames = daemon.pipeline.stats.frames
        wait_for(lambda: daemon.pipeline.stats.frames > frames + 20, "tracking going on")

        r = mocapd_cli("status", "--json", tmp_path / "status.json", "--runtime-dir", rt)
        assert r.code == 0, r.err
        st = json.loads((tmp_path / "status.json").read_text())
        assert st["view"]["alive"] and st["view"]["restarts"] == 1
        assert st["view"]["last_exit"] == -signal.SIGKILL and st["view"]["pid"] != first
        # and the plain status says it in one line
        assert f"view: {st['view']['url']} serving, started again 1 time (last exit -9)" in r.out
        feed = _thread(st, "view-feed")
        assert feed["state"] == "running" and feed["restarts"] == 1
        assert feed["last_error"].startswith("ViewEnded: the live view process has ended")
        said = [r.getMessage() for r in caplog.records
                if "view" in r.getMessage() and r.name.startswith("mocapd")]
        assert len([m for m in said if m.startswith("view-feed: thread failed")]) == 1, said
        assert len([m for m in said if m.startswith("live view restarted")]) == 1, said
    finally:
        _stop(daemon, thread)
    assert not daemon.view.process.is_alive()


# ---- the Zenoh session and the pinger --------------------------------------------------------

def _listener(endpoint: str, key: str):
    """A Zenoh session of the test's own joined to the daemon's, counting `key`'s samples."""
    from daemon.publish.zenoh_session import ZenohSettings

    got = []
    session = ZenohSettings(connect=(endpoint,)).open()
    session.declare_subscriber(key, lambda s: got.append(s.payload.to_bytes()))
    return session, got


@pytest.fixture
def zenoh_daemon(tmp_path):
    endpoint = f"tcp/127.0.0.1:{_free_tcp_port()}"
    daemon, thread, rt = _run_daemon(
        tmp_path, SIM + f'[zenoh]\nrig = "lab"\nlisten = ["{endpoint}"]\n')
    yield daemon, endpoint, rt
    _stop(daemon, thread)
    assert all(t["state"] == "stopped" for t in
               (s.status() for s in daemon.hub.supervised))


def test_a_pinger_that_raises_is_restarted(zenoh_daemon, caplog):
    from daemon.publish.zenoh_session import ping_key

    daemon, endpoint, _ = zenoh_daemon
    hub = daemon.hub
    assert _thread(daemon.status(), "node-clocks") == {
        "name": "node-clocks", "state": "running", "restarts": 0, "last_error": None}
    caplog.set_level(logging.ERROR, "mocapd")
    hit = threading.Event()

    class Watchdog:  # stands in for a remote camera's watchdog check, which fails once
        def check(self, now_ns):
            if not hit.is_set():
                hit.set()
                raise Boom("watchdog")

    session, pings = _listener(endpoint, ping_key("lab"))
    try:
        hub._captures = [Watchdog()]
        wait_for(hit.is_set, "the pinger meeting the failure")
        wait_for(lambda: _thread(daemon.status(), "node-clocks")["restarts"] == 1
                 and _thread(daemon.status(), "node-clocks")["state"] == "running",
                 "the pinger restarted")
        n = len(pings)
        wait_for(lambda: len(pings) > n + 10, "pings going out after the restart")
    finally:
        session.close()
    assert _thread(daemon.status(), "node-clocks")["last_error"] == "Boom: watchdog"
    said = [r.getMessage() for r in caplog.records if r.name == "mocapd.supervise"]
    assert said == ["node-clocks: thread failed (Boom: watchdog), restarting it"]


def test_a_closed_zenoh_session_is_reopened_and_carries_poses_again(zenoh_daemon, caplog):
    from daemon.publish import zenoh_wire as wire
    from daemon.publish.zenoh_session import ping_key
    from daemon.service.control import request

    daemon, endpoint, rt = zenoh_daemon
    hub = daemon.hub
    caplog.set_level(logging.WARNING, "mocapd")
    old = hub.session
    old.close()  # as a session Zenoh (or a bug) closed under the daemon
    wait_for(lambda: hub.reopened == 1 and hub.session is not old
             and not hub.session.is_closed(), "the session reopened")
    # a client joining now gets the poses (the Zenoh output reopened on the new session)
    # and the clock pings
    session, poses = _listener(endpoint, "mocap/lab/bodies/*")
    pings = []
    session.declare_subscriber(ping_key("lab"), lambda s: pings.append(1))
    try:
        wait_for(lambda: len(poses) > 20 and len(pings) > 5, "poses and pings on the new "
                 "session")
        first, last = wire.decode_pose(poses[0]), wire.decode_pose(poses[-1])
        assert last["id"] in {int(b.id) for b in daemon.pipeline.rigid.bodies}
        assert last["frame"] > first["frame"]  # a live stream, not one message
    finally:
        session.close()
    st = request(rt, {"cmd": "status"}, timeout_s=10.0)  # what `mocapd status --json` shows
    watch = _thread(st, "zenoh-session")
    assert watch["state"] == "running" and watch["restarts"] == 1
    assert watch["last_error"] == "SessionLost: the Zenoh session closed"
    out = next(o for o in st["outputs"] if o["name"].startswith("zenoh:"))
    assert out["connected"] and out["errors"] >= 1  # it met the closed session, reopened
    said = [r.getMessage() for r in caplog.records if "zenoh" in r.getMessage()]
    assert len([m for m in said if m.startswith("zenoh-session: thread failed")]) == 1, said
    assert len([m for m in said if m.startswith("zenoh: session reopened")]) == 1, said
