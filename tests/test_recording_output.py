"""Recording outputs (daemon/publish/recording_output.py): a full disk or an I/O error ends a
recording and keeps every frame written before it; a file is never reopened, truncated or
overwritten."""

from __future__ import annotations

import errno
import time
from types import SimpleNamespace

import numpy as np
import pytest

from calibkit.core.recording import RecordingWriter, load_observations
from calibkit.synthetic import sim
from daemon.publish import recording_output
from daemon.publish.recorder import RecorderPublisher

RIG = sim.make_rig(3, 4.0, seed=0)


def _result(frame: int):
    samples = [SimpleNamespace(camera=c, t_ns=frame * 1_000_000 + c, uv=np.full((2, 2), frame + c),
                               area=np.ones(2), peak=np.full(2, 200.0)) for c in range(3)]
    return SimpleNamespace(frame=frame, arrival_ns=time.monotonic_ns(), samples=samples)


def _wait(cond, what: str, timeout_s: float = 30.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not cond():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.01)


def test_a_full_disk_ends_the_recording_and_keeps_what_was_written(tmp_path, monkeypatch):
    """The disk fills after 40 frames' lines: the recording stops there for good (the old
    recorder reopened the file with "w" every 5 s, truncating it), status says why at
    once, and the file reads back those 40 frames."""
    real_write, lines = RecordingWriter._write, []

    def filling(self, record):
        if len(lines) >= 1 + 40 * 3:  # the header, then 40 frames of 3 cameras
            raise OSError(errno.ENOSPC, "No space left on device")
        lines.append(record)
        real_write(self, record)

    monkeypatch.setattr(RecordingWriter, "_write", filling)
    path = tmp_path / "take.mcrec"
    rec = RecorderPublisher(path, RIG, 100.0)
    rec.start()
    for f in range(100):
        rec.submit(_result(f))
    _wait(lambda: rec.sent + rec.lost == 100, "every frame handled")
    st = rec.status()
    assert rec.sent == 40 and rec.lost == 60 and rec.errors == 1
    assert "No space left" in st["failed"] and "recording stopped" in st["last_error"]
    time.sleep(0.2)
    rec.submit(_result(100))  # long after the failure: still no reopen
    _wait(lambda: rec.lost == 61, "the late frame counted as lost")
    rec.stop()
    obs, _ = load_observations(path)
    assert obs.frames().tolist() == list(range(40))
    np.testing.assert_allclose(obs.uv[obs.frame == 39][0], [39, 39])


def test_the_free_space_floor_stops_a_recording_before_the_disk_is_full(tmp_path):
    floor_mb = recording_output.free_mb(tmp_path) + 1e6  # more than any disk here has free
    path = tmp_path / "take.mcrec"
    rec = RecorderPublisher(path, RIG, 100.0, min_free_mb=floor_mb)
    rec.start()
    rec.submit(_result(0))
    _wait(lambda: rec.failed, "the floor to stop it")
    rec.stop()
    assert "under the floor" in rec.failed and rec.sent == 0
    obs, _ = load_observations(path)  # the header was written: the file is a recording
    assert len(obs) == 0


def test_a_recording_is_never_written_over_an_existing_file(tmp_path):
    from daemon.config.mocapd import parse_config
    from daemon.service.daemon import Daemon

    d = Daemon(parse_config({"runtime_dir": str(tmp_path / "rt"), "sim": {"cameras": 3}}))
    d.setup(10)
    try:
        kept = tmp_path / "kept.mcrec"
        kept.write_text("an earlier take\n")
        from calibkit.core.errors import UserError

        with pytest.raises(UserError, match="exists"):
            d.handle({"cmd": "record", "path": str(kept)})
        assert kept.read_text() == "an earlier take\n"
        with pytest.raises(UserError, match="does not exist"):
            d.handle({"cmd": "record", "path": str(tmp_path / "no" / "x.mcrec")})
        for bad in (str(tmp_path / "x\0.mcrec"), ["x.mcrec"], 7,  # said now, not at a frame
                    str(tmp_path / ("é" * 300 + ".mcrec"))):           # nor as a traceback
            with pytest.raises(UserError, match="NUL|needs a PATH|too long"):
                d.handle({"cmd": "record", "path": bad})
            assert d.recorder is None
        assert d.handle({"cmd": "record", "path": str(kept), "overwrite": True})["ok"]
        assert d.status()["recording_status"]["failed"] is None
        stopped = d.handle({"cmd": "record_stop"})
        assert stopped["failed"] is None and stopped["lost"] == 0
    finally:
        d.shutdown()
