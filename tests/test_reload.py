"""Reloading a running daemon (SIGHUP, `mocapd reload`): the new configuration, rig file
included, is read and checked in full, then swapped in between two frames; any failure keeps
the running one and says why."""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import replace

import pytest

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


@pytest.fixture
def running(tmp_path):
    cfg_path = tmp_path / "mocapd.toml"
    cfg_path.write_text(SIM)
    rt = tmp_path / "rt"
    daemon = Daemon(replace(load_config(cfg_path), runtime_dir=rt),
                    extend=lambda c: replace(c, runtime_dir=rt))
    thread = threading.Thread(target=daemon.run, kwargs={"duration_s": 120.0}, daemon=True)
    thread.start()
    deadline = time.monotonic() + 90
    while getattr(daemon, "pipeline", None) is None or daemon.pipeline.stats.frames < 20:
        assert time.monotonic() < deadline and thread.is_alive(), "the daemon did not start"
        time.sleep(0.05)
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
