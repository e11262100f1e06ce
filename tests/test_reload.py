"""Reloading a running daemon (SIGHUP, `mocapd reload`): the new configuration, rig file
included, is read and checked in full, then swapped in between two frames; any failure keeps
the running one and says why."""

from __future__ import annotations

import logging
import socket
import threading
import time
from dataclasses import replace

import pytest

from calibkit.core.errors import UserError
from daemon.config.mocapd import load_config
from daemon.service.daemon import Daemon

SIM = "[sim]\ncameras = 4\nbodies = 2\nfps = 100.0\nseed = 5\n"


def _frames_after(daemon, n: int, timeout_s: float = 60.0) -> None:
    """Wait until the frame loop has tracked n more frames (a reload applies between two)."""
    start = daemon.pipeline.stats.frames
    deadline = time.monotonic() + timeout_s
    while daemon.pipeline.stats.frames < start + n:
        assert time.monotonic() < deadline, "the daemon stopped tracking"
        time.sleep(0.02)


def _run_with(tmp_path, text: str, duration_s: float = 120.0):
    """A daemon running the configuration `text`, tracking: (daemon, its file, thread)."""
    cfg_path = tmp_path / "mocapd.toml"
    cfg_path.write_text(text)
    rt = tmp_path / "rt"
    daemon = Daemon(replace(load_config(cfg_path), runtime_dir=rt),
                    extend=lambda c: replace(c, runtime_dir=rt))
    thread = threading.Thread(target=daemon.run, kwargs={"duration_s": duration_s}, daemon=True)
    thread.start()
    deadline = time.monotonic() + 90
    while getattr(daemon, "pipeline", None) is None or daemon.pipeline.stats.frames < 20:
        assert time.monotonic() < deadline and thread.is_alive(), "the daemon did not start"
        time.sleep(0.05)
    return daemon, cfg_path, thread


@pytest.fixture
def running(tmp_path):
    daemon, cfg_path, thread = _run_with(tmp_path, SIM)
    yield daemon, cfg_path
    daemon.handle({"cmd": "stop"})
    thread.join(30)
    assert not thread.is_alive()


def test_every_reachable_reload_keeps_tracking(running, tmp_path, caplog):
    daemon, cfg_path = running
    assert len(daemon.pipeline.rigid.bodies) == 2
    # the last bodies removed: zero bodies (this crashed the next frame before)
    cfg_path.write_text(SIM.replace("bodies = 2\n", "bodies = 2\ndefine_bodies = false\n"))
    assert daemon.reload()
    _frames_after(daemon, 20)
    assert daemon.pipeline.rigid.bodies == [] and daemon.status()["bodies"] == []
    # and back: the bodies come again
    cfg_path.write_text(SIM)
    assert daemon.reload()
    _frames_after(daemon, 20)
    assert len(daemon.pipeline.rigid.bodies) == 2
    # a rig file that is missing or cut short fails the reload: nothing changes
    tracker = daemon.pipeline.tracker
    with caplog.at_level(logging.ERROR, "mocapd"):
        cfg_path.write_text(f'rig = "{tmp_path / "gone.toml"}"\n' + SIM)
        assert not daemon.reload()
        daemon.rig.save(tmp_path / "cut.toml")
        text = (tmp_path / "cut.toml").read_text()
        (tmp_path / "cut.toml").write_text(text[: len(text) // 2])
        cfg_path.write_text(f'rig = "{tmp_path / "cut.toml"}"\n' + SIM)
        assert not daemon.reload()
    failed = [r.getMessage() for r in caplog.records if "reload failed" in r.getMessage()]
    assert len(failed) == 2 and "gone.toml" in failed[0] and "cut.toml" in failed[1]
    _frames_after(daemon, 10)
    assert daemon.pipeline.tracker is tracker and len(daemon.pipeline.rigid.bodies) == 2
    # new tracker gates: a new tracker, swapped between frames, and tracking goes on
    cfg_path.write_text(SIM + "[tracker]\ngate_px = 7.5\n")
    assert daemon.reload()
    _frames_after(daemon, 30)
    assert daemon.pipeline.tracker is not tracker
    assert daemon.pipeline.tracker.config.gate_px == 7.5
    assert daemon.status()["bodies_tracked"] >= 1


def test_the_stream_goes_on_while_a_reload_is_read_and_built(running, monkeypatch):
    """SIGHUP's reload runs beside the frame loop: a reload held up half way (a slow disk,
    a big marker set) does not hold up a single frame; the frame loop only swaps."""
    daemon, _cfg = running
    inside, release = threading.Event(), threading.Event()
    real = daemon._warn_alike

    def slow(bodies):
        inside.set()
        assert release.wait(60)
        real(bodies)

    monkeypatch.setattr(daemon, "_warn_alike", slow)
    ticket = daemon.reloads.asked + 1
    daemon.reload_event.set()  # as SIGHUP does
    assert inside.wait(60), "the frame loop did not start the reload"
    frames = daemon.pipeline.stats.frames
    _frames_after(daemon, 30)  # tracked while the reload is stuck
    assert daemon.pipeline.stats.frames >= frames + 30
    release.set()
    assert daemon.reloads.wait(ticket, 60) == (True, None)


def test_a_reloads_steps_wait_for_the_gap_after_a_frame(running):
    """after_frame returns once a frame has gone to the outputs after the call (a reload's
    step then has the gap until the next frame to itself), or after its timeout when no
    frame comes: a stopped stream does not hold a reload up for good."""
    daemon, _cfg = running
    pipeline = daemon.pipeline
    for _ in range(5):
        called = time.monotonic_ns()
        pipeline.after_frame(60.0)
        assert pipeline.last_result.published_ns >= called
    pipeline.process, process = (lambda fs: None), pipeline.process  # no frame goes out
    try:
        waited = time.monotonic()
        pipeline.after_frame(0.3)
        assert time.monotonic() - waited >= 0.29
    finally:
        pipeline.process = process


def test_a_failed_reload_is_said_to_whoever_asked(running):
    daemon, cfg_path = running
    cfg_path.write_text(SIM + "[tracker]\ngate_mm = 40\n")
    with pytest.raises(UserError, match="gate_mm"):
        daemon.handle({"cmd": "reload"})
    cfg_path.write_text(SIM)
    assert daemon.handle({"cmd": "reload"}) == {"ok": True}


def test_outputs_not_changed_by_a_reload_go_on_and_removed_ones_stop(tmp_path):
    """An output whose table did not change keeps its socket, thread and counts through a
    reload; one the new file drops is stopped (its thread ends), one it adds starts."""
    readers = [socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in range(2)]
    for r in readers:
        r.bind(("127.0.0.1", 0))
    a, b = (r.getsockname()[1] for r in readers)
    one = SIM + f'\n[[udp]]\naddress = "127.0.0.1:{a}"\n'
    two = one + f'\n[[udp]]\naddress = "127.0.0.1:{b}"\n'
    daemon, cfg_path, thread = _run_with(tmp_path, two)
    try:
        first, second = daemon.pipeline.publishers
        cfg_path.write_text(one)
        assert daemon.reload()
        _frames_after(daemon, 10)
        assert daemon.pipeline.publishers == [first]
        sent = first.sent
        assert not second._worker.thread.is_alive()
        _frames_after(daemon, 10)
        assert first.sent > sent and first._worker.thread.is_alive()
        cfg_path.write_text(two)
        assert daemon.reload()
        _frames_after(daemon, 10)
        kept, added = daemon.pipeline.publishers
        assert kept is first and added is not second and added._worker.thread.is_alive()
    finally:
        daemon.handle({"cmd": "stop"})
        thread.join(30)
        for r in readers:
            r.close()
    assert not thread.is_alive()


def test_new_gates_keep_the_tracks_and_the_bodies_on_them(running):
    """A reload that changes only the tracker's gates hands the running tracks to the new
    tracker: the markers keep their ids, and the bodies stay tracked through the swap."""
    daemon, cfg_path = running
    valid = []
    daemon.pipeline.hooks.append(lambda r: valid.append(bool(r.poses.valid.all())))
    _frames_after(daemon, 20)
    assert all(valid[-10:]), "both bodies tracked before the reload"
    before = set(daemon.pipeline.tracker.ids.tolist())
    old = daemon.pipeline.tracker
    cfg_path.write_text(SIM + "[tracker]\ngate_px = 4.0\n")
    mark = len(valid)
    assert daemon.reload()
    _frames_after(daemon, 10)
    assert daemon.pipeline.tracker is not old
    assert daemon.pipeline.tracker.config.gate_px == 4.0
    after = set(daemon.pipeline.tracker.ids.tolist())
    assert len(before & after) >= 0.8 * len(before)
    assert all(valid[mark:]), "a body lost at the swap"
