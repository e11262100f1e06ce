"""What a long run keeps stays bounded (issue 30): the pipeline's whole-run figures are a
fixed-size sample whose median and p99 are still the run's, and a daemon run through a
reload and a recording keeps no more than that sample (benchmarks/soak.py is the long run)."""

from __future__ import annotations

import json
import threading
import time
from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest

from daemon.capture import pipeline
from daemon.capture.pipeline import Stats, latency_figures, latency_stage_figures
from daemon.config.mocapd import load_config
from daemon.service.daemon import Daemon


def _result(k: int, latency_ns: int, seen: int) -> SimpleNamespace:
    """The fields of a FrameResult that Stats reads, for frame k."""
    t = k * 4_000_000
    return SimpleNamespace(
        done_ns=t + 100 + latency_ns, arrival_ns=t + 100, t_ns=t, pickup_ns=t + 150,
        published_ns=t + 200 + latency_ns,
        poses=SimpleNamespace(ids=np.array([1, 2]), valid=np.array([True, k % 2 == 0])),
        tracks=SimpleNamespace(seen=np.ones(seen, dtype=bool)))


def test_stats_keep_a_bounded_sample_whose_percentiles_are_the_runs():
    rng = np.random.default_rng(3)
    n, size = 40_000, 4000
    # a latency that drifts over the run (a slow second half): a sample of the recent frames
    # or of the first ones would get the median wrong; a uniform one of the whole run not
    lat = np.concatenate([rng.gamma(4.0, 150_000.0, n // 2),
                          rng.gamma(4.0, 300_000.0, n - n // 2)]).astype(np.int64)
    st = Stats(window=256, sample_size=size, seed=1)
    for k in range(n):
        st.add(_result(k, int(lat[k]), 5 + k % 7))
    assert st.frames == n
    assert len(st.all_latency) == size and st.stage_ns.shape == (size, 5)
    assert len(st.latency) == 256 and len(st.done) == 256
    got = latency_figures(st.all_latency)
    true_med, true_p99 = np.median(lat) * 1e-6, np.percentile(lat, 99) * 1e-6
    # sampling error of a quantile from 4000 draws: a few percent at most
    assert got["median_ms"] == pytest.approx(true_med, rel=0.05)
    assert got["p99_ms"] == pytest.approx(true_p99, rel=0.08)
    # every sampled row is one frame's, and the first frames stay out of stage_ns[skip:]
    t0 = st.stage_ns[:, 0]
    assert np.all(t0[200:] >= 200 * 4_000_000)
    assert np.array_equal(st.stage_ns[:, 3] - st.stage_ns[:, 1], st.all_latency)
    # the counts are exact, not sampled
    assert st.body_frames == {1: n, 2: n} and st.body_valid == {1: n, 2: n // 2}
    assert set(np.unique(st.markers_seen)) <= set(range(5, 12))
    assert latency_stage_figures(st.stage_ns, skip=200)["compute"]["median_ms"] > 0


def test_stats_are_exact_until_the_sample_is_full():
    st = Stats(sample_size=100)
    for k in range(60):
        st.add(_result(k, 1000 * (k + 1), 3))
    assert np.array_equal(st.all_latency, 1000 * np.arange(1, 61))
    assert latency_figures(st.all_latency)["count"] == 60


SIM = "[sim]\ncameras = 4\nbodies = 2\nfps = 100.0\nseed = 5\n"


def test_daemon_through_a_reload_and_a_recording_keeps_its_figures_bounded(tmp_path,
                                                                            monkeypatch):
    monkeypatch.setattr(pipeline, "SAMPLE_FRAMES", 300)
    cfg_path = tmp_path / "mocapd.toml"
    cfg_path.write_text(SIM)
    rt = tmp_path / "rt"
    daemon = Daemon(replace(load_config(cfg_path), runtime_dir=rt),
                    extend=lambda c: replace(c, runtime_dir=rt))
    thread = threading.Thread(target=daemon.run, kwargs={"duration_s": 120.0}, daemon=True)
    thread.start()

    def frames_at_least(n: int, timeout_s: float = 90.0) -> None:
        deadline = time.monotonic() + timeout_s
        while getattr(daemon, "pipeline", None) is None or daemon.pipeline.stats.frames < n:
            assert time.monotonic() < deadline and thread.is_alive(), "the daemon stalled"
            time.sleep(0.05)

    try:
        frames_at_least(100)
        # a fault: a body removed by a reload, then a recording across it
        learned = (rt / "sim-bodies.toml").read_text()
        one_body = "[[rigid_body]]".join(learned.split("[[rigid_body]]")[:-1])
        cfg_path.write_text(SIM + "\n" + one_body)
        assert daemon.handle({"cmd": "reload"})["ok"]
        rec = tmp_path / "take.mcrec"
        before = daemon.pipeline.stats.frames
        assert daemon.handle({"cmd": "record", "path": str(rec)})["ok"]
        frames_at_least(before + 150)
        stopped = daemon.handle({"cmd": "record_stop"})
        after = daemon.pipeline.stats.frames
        assert stopped["ok"] and not stopped["lost"]
        with open(rec, encoding="utf-8") as f:
            f.readline()
            frames = {json.loads(line)["f"] for line in f}
        # every frame tracked while recording is in the file (the set numbers may skip
        # where the multiplexer dropped a set: those were never tracked)
        assert 140 <= len(frames) == stopped["frames"] <= after - before
        frames_at_least(700)
        st = daemon.pipeline.stats
        assert len(daemon.pipeline.rigid.bodies) == 1
        assert st.frames >= 700
        assert len(st.all_latency) == 300 and len(st.stage_ns) == 300
        assert len(st.latency) <= 2048 and len(st.done) <= 2048
        assert daemon.pipeline.idle_pending <= pipeline.IDLE_BACKLOG
        assert len(daemon.pipeline.hooks) == 0  # the recorder's hook went with it
    finally:
        daemon.handle({"cmd": "stop"})
        thread.join(30)
    assert not thread.is_alive()
    fig = daemon.figures()
    assert fig["frames"] >= 700 and fig["latency_to_poses"]["count"] == 300
    assert 0 < fig["latency_to_poses"]["median_ms"] <= fig["latency_to_poses"]["p99_ms"]
    assert fig["markers_tracked_median"] > 0


def test_the_sim_ledger_is_fixed_in_size_and_keeps_the_recent_frames_of_each_session():
    from daemon.synthetic.ledger import WAYS, Ledger

    cap = 1024
    led = Ledger(2, cap)
    nbytes = sum(a.nbytes for a in vars(led).values() if isinstance(a, np.ndarray))
    # session 1 of camera 1: 5000 frames, device clock from an epoch; then a reconnect:
    # ids from 0 again on a new epoch, 300 frames
    dev1 = 7_000_000_000 + 4_166_667 * np.arange(5000)
    for k in range(5000):
        led.add(1, k, int(dev1[k]), 10 * k, 100 + k)
    dev2 = 9_000_000_000 + 4_166_667 * np.arange(300)
    for k in range(300):
        led.add(1, k, int(dev2[k]), 50_000 + k, 900 + k)
    assert sum(a.nbytes for a in vars(led).values() if isinstance(a, np.ndarray)) == nbytes
    # the new session's frames, and the old session's latest beside them: in every set,
    # the ways the new session did not take (300 frames over 256 sets take up to 2)
    assert all(led.get(1, k, int(dev2[k])) == (50_000 + k, 900 + k) for k in range(300))
    taken_ways = -(-300 // led.sets)
    assert led.sets == cap // WAYS and taken_ways < WAYS
    recent = range(5000 - (WAYS - taken_ways) * led.sets, 5000)
    assert all(led.get(1, k, int(dev1[k])) == (10 * k, 100 + k) for k in recent)
    # forgotten: the oldest frames; never held: the other camera, a wrong device time
    assert led.get(1, 10, int(dev1[10])) is None
    assert led.get(0, 4999, int(dev1[4999])) is None
    assert led.get(1, 4999, int(dev1[4999]) + 1) is None
    assert led.get(1, -1, -1) is None
