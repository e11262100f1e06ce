"""A node's blob set goes into the multiplexer as one batch: decoded as arrays, its times
mapped through the node's clock in one call, one push per message, frame sets as sent."""

from __future__ import annotations

import time
from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from daemon.capture.multiplexer import Multiplexer
from daemon.nodes.clock import NodeClock
from daemon.nodes.remote import NodeHub
from daemon.publish import zenoh_wire as wire

RIG = "batch"
OFFSET_NS = 3_700_000_000  # the node's clock is 3.7 s ahead of the daemon's


class _Payload:
    def __init__(self, data):
        self.data = data

    def to_bytes(self):
        return self.data


def _zenoh_sample(key, data):
    return SimpleNamespace(key_expr=key, payload=_Payload(data))


class _CountingMux(Multiplexer):
    """The multiplexer, counting how it is called."""

    def __init__(self, *a, **k):
        super().__init__(*a, **k)
        self.calls = {"push": 0, "push_many": 0}

    def push(self, sample):
        self.calls["push"] += 1
        super().push(sample)

    def push_many(self, samples):
        self.calls["push_many"] += 1
        super().push_many(samples)


def _hub(names, mux, boot=9):
    settings = SimpleNamespace(session=SimpleNamespace(rig=RIG), timeout_ms=1e9,
                               max_lag_ms=1e9)
    hub = NodeHub(settings, names, {n: n for n in names})
    node = hub._node("n1", boot)
    for i in range(10):  # exchanges of a 10 us link to a clock OFFSET_NS ahead
        t1 = 10**9 + i * 50_000_000
        node.clock.add(t1, t1 + 5_000 + OFFSET_NS, t1 + 6_000 + OFFSET_NS, t1 + 11_000)
    for cap in hub.sources():
        cap.push, cap.on_open = mux.push, mux.reset_camera
        cap.start()
    return hub


def _set_message(names, k, t0, rng, boot=9, counts=None):
    """The node's frames of trigger k (times on the node's clock), and their blobs."""
    t = t0 + round(k * 1e9 / 240) + OFFSET_NS
    frames = []
    for c, name in enumerate(names):
        n = 3 + c if counts is None else counts[c]
        frames.append((name.encode(), k, t, t + 900_000, -1, -1, rng.uniform(0, 1280, (n, 2)),
                       rng.uniform(2, 40, n), rng.uniform(50, 255, n)))
    return wire.encode_sets(boot, k, t + 1_000_000, frames), frames


def test_sets_arrays_match_the_per_frame_decoder():
    rng = np.random.default_rng(4)
    names = ["a", "bb", "ccc"]
    data, frames = _set_message(names, 3, 10**12, rng, counts=[4, 0, 7])
    m = wire.decode_sets_arrays(data)
    per_frame = wire.decode_sets(data)
    assert m.names == names == [n for n, _ in per_frame]
    assert m.ends == [4, 4, 11]
    assert m.table["t_ns"].tolist() == [f[2] for f in frames]
    a = 0
    for (_, msg), b in zip(per_frame, m.ends, strict=True):
        np.testing.assert_array_equal(m.uv[a:b], msg.uv)
        a = b
    np.testing.assert_allclose(m.uv, np.concatenate([f[6] for f in frames]), atol=1e-3)


def test_to_daemon_array_agrees_with_to_daemon_under_offset_and_drift():
    clock = NodeClock()
    for i in range(120):  # six seconds of exchanges: long enough that drift is fitted
        t1 = 10**12 + i * 50_000_000
        t2 = t1 + 5_000 + 2_500_000_000 + round(40e-6 * (t1 - 10**12))
        clock.add(t1, t2, t2 + 1_000, t1 + 11_000)
    assert clock.fit[1] != 0.0
    node_ns = 10**12 + 2_500_000_000 + np.arange(0, 7_000_000_000, 123_456_789)
    got = clock.to_daemon_array(node_ns)
    assert got.dtype == np.int64
    assert np.abs(got - np.array([clock.to_daemon(int(t)) for t in node_ns])).max() <= 1


def test_one_push_per_message_and_frame_sets_hold_what_the_node_sent():
    names = [f"cam{c}" for c in range(4)]
    mux = _CountingMux(len(names), fps=240.0)
    hub = _hub(names, mux)
    rng = np.random.default_rng(7)
    t0 = time.monotonic_ns()
    sent, got = [], []
    for k in range(30):  # the frame loop takes each set as it comes (it keeps 2 at most)
        data, frames = _set_message(names, k, t0, rng)
        sent.append(frames)
        hub._on_sets(_zenoh_sample(f"mocap/{RIG}/_nodes/n1/blobs", data))
        got.append(mux.next(30.0))
    assert hub.bad == 0
    assert mux.calls == {"push": 0, "push_many": 30}
    assert None not in got and mux.skipped == 0
    assert mux.incomplete == 0
    for fs, frames in zip(got, sent, strict=True):
        assert [s.camera for s in fs.samples] == [0, 1, 2, 3]
        truth_t = frames[0][2] - OFFSET_NS  # on the daemon's clock
        # the clock estimate from a symmetric 10 us link: within a microsecond
        assert abs(fs.t_ns - truth_t) < 1_000
        for s, f in zip(fs.samples, frames, strict=True):
            assert s.index == f[1]
            assert abs(s.arrival_ns - (f[3] - OFFSET_NS)) < 1_000
            np.testing.assert_allclose(s.uv, f[6], atol=1e-3)
            np.testing.assert_allclose(s.area, f[7], rtol=1e-6)
    st = hub.status()[0]
    assert st["samples"] == 120 and st["hop_median_ms"] is not None


def test_a_set_with_a_camera_the_daemon_does_not_take_counts_it_and_passes_the_rest():
    names = ["cam0", "cam1"]
    mux = _CountingMux(2, fps=240.0)
    hub = _hub(names, mux)
    rng = np.random.default_rng(1)
    data, _ = _set_message(["cam0", "stranger", "cam1"], 0, time.monotonic_ns(), rng)
    hub._on_sets(_zenoh_sample(f"mocap/{RIG}/_nodes/n1/blobs", data))
    assert hub.unknown == 1
    fs = mux.next(5.0)
    assert fs is not None and [s.camera for s in fs.samples] == [0, 1]


def test_a_set_from_a_node_whose_clock_is_unknown_waits_and_a_bad_version_is_refused():
    names = ["cam0"]
    mux = _CountingMux(1, fps=240.0)
    hub = _hub(names, mux)
    rng = np.random.default_rng(2)
    data, _ = _set_message(names, 0, time.monotonic_ns(), rng, boot=55)
    hub._node("n2", 55)  # heard, but no clock exchange yet
    hub._on_sets(_zenoh_sample(f"mocap/{RIG}/_nodes/n2/blobs", data))
    assert hub.nodes[55].waiting_clock == 1 and mux.calls["push_many"] == 0
    future = bytearray(data)
    future[2] = wire.VERSION + 1
    with pytest.raises(wire.WireError, match="not a version"):
        wire.decode_sets_arrays(bytes(future))
    hub._on_sets(_zenoh_sample(f"mocap/{RIG}/_nodes/n2/blobs", bytes(future)))
    assert hub.bad == 1


@settings(max_examples=400, deadline=None)
@given(data=st.data())
def test_the_array_decoder_refuses_any_corruption_with_a_wire_error_or_decodes_it_whole(data):
    """Bytes changed, cut or added anywhere in a good message: a WireError, or a message
    whose parts agree (never another exception, never blobs past the frames' counts)."""
    rng = np.random.default_rng(data.draw(st.integers(0, 2**32 - 1)))
    counts = data.draw(st.lists(st.integers(0, 4), min_size=0, max_size=4))
    names = [f"c{k}" for k in range(len(counts))]
    good, _ = _set_message(names, 1, 10**12, rng, counts=counts)
    msg = bytearray(good)
    for _ in range(data.draw(st.integers(0, 6))):
        msg[data.draw(st.integers(0, len(msg) - 1))] = data.draw(st.integers(0, 255))
    cut = data.draw(st.integers(0, len(msg) + 8))
    raw = bytes(msg[:cut]) + data.draw(st.binary(max_size=8)) if cut < len(msg) else bytes(msg)
    try:
        m = wire.decode_sets_arrays(raw)
    except wire.WireError:
        return
    assert len(m.names) == len(m.table) == len(m.ends)
    assert (m.ends[-1] if m.ends else 0) == len(m.uv) == len(m.area) == len(m.peak)
    assert np.isfinite(m.uv).all()
