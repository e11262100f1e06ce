"""Zenoh messages the daemon decodes from nodes (blobs, blob sets, clock round trips,
announcements) with random and corrupted payloads: nothing escapes the callbacks, bad
messages are counted and logged once per kind, good ones still arrive (issue 30)."""

from __future__ import annotations

import json
import logging
import time
from types import SimpleNamespace

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from daemon.nodes.remote import NodeHub
from daemon.publish import zenoh_wire as wire

RIG = "lab"


class Payload:
    def __init__(self, data: bytes) -> None:
        self.data = data

    def to_bytes(self) -> bytes:
        return self.data


def sample(key: str, data: bytes):
    """What Zenoh hands a subscriber's callback: a key expression and a payload."""
    return SimpleNamespace(key_expr=key, payload=Payload(data))


def hub() -> NodeHub:
    """A hub that is never started (no session): its callbacks are called by hand."""
    settings_ = SimpleNamespace(session=SimpleNamespace(rig=RIG))
    return NodeHub(settings_, ["cam0", "cam1"], {"cam0": "cam0", "cam1": "cam1"})


class Capture:
    def __init__(self) -> None:
        self.samples = []

    def deliver(self, s, node, has) -> None:
        self.samples.append(s)


def good_messages(boot: int = 7):
    uv = np.array([[10.5, 20.25], [300.0, 40.0]])
    frame = (b"cam0", 5, 1000, 1100, -1, -1, uv, np.ones(2), np.full(2, 200.0))
    return {
        "blobs": wire.encode_blobs(boot, 1, 5, 1000, 1100, 1200, -1, -1, uv, np.ones(2),
                                   np.full(2, 200.0)),
        "sets": wire.encode_sets(boot, 1, 1200, [frame, (b"cam1", *frame[1:])]),
        "clock": wire.encode_pong(boot, 1, 10, 20, 30),
        "announce": json.dumps({"node": "n1", "boot": boot, "cameras": ["cam0"]}).encode()}


KEYS = {"blobs": f"mocap/{RIG}/cam0/blobs", "sets": f"mocap/{RIG}/_nodes/n1/blobs",
        "clock": f"mocap/{RIG}/_nodes/n1/clock", "announce": f"mocap/{RIG}/_nodes/n1/announce"}


def deliver(h: NodeHub, kind: str, data: bytes) -> None:
    {"blobs": h._on_blobs, "sets": h._on_sets, "clock": h._on_pong,
     "announce": h._on_announce}[kind](sample(KEYS[kind], data))


@st.composite
def corrupted(draw):
    kind = draw(st.sampled_from(sorted(KEYS)))
    data = bytearray(good_messages(draw(st.integers(0, 2 ** 32 - 1)))[kind])
    for _ in range(draw(st.integers(0, 6))):
        data[draw(st.integers(0, len(data) - 1))] = draw(st.integers(0, 255))
    cut = draw(st.integers(0, len(data) + 8))
    data = bytes(data[:cut]) + draw(st.binary(max_size=8)) if cut < len(data) else bytes(data)
    return kind, data


JSONISH = st.recursive(st.none() | st.booleans() | st.integers() | st.floats() | st.text(),
                       lambda c: st.lists(c, max_size=4) | st.dictionaries(st.text(), c,
                                                                           max_size=4),
                       max_leaves=8)

_HUB = hub()


@settings(max_examples=500, deadline=None)
@given(msgs=st.lists(st.one_of(
    st.tuples(st.sampled_from(sorted(KEYS)), st.binary(max_size=200)), corrupted(),
    st.tuples(st.just("announce"), st.builds(
        lambda v: json.dumps(v).encode(),
        st.fixed_dictionaries({"node": JSONISH, "boot": JSONISH, "cameras": JSONISH})))),
    min_size=1, max_size=5))
def test_no_payload_escapes_a_callback(msgs):
    for kind, data in msgs:
        deliver(_HUB, kind, data)  # raises nothing, whatever the bytes
    assert _HUB.bad == sum(_HUB.refused.counts.values())


def test_good_messages_arrive_among_junk_and_junk_is_logged_once_per_kind(caplog):
    h = hub()
    caps = [Capture(), Capture()]
    for cam, cap in zip(h.cameras.values(), caps, strict=True):
        cam.capture = cap
    rng = np.random.default_rng(30)
    good = good_messages()
    with caplog.at_level(logging.INFO, "mocapd"):
        deliver(h, "announce", good["announce"])
        t = time.monotonic_ns()
        for k in range(12):  # clock round trips: the node's clock 1 ms ahead of ours
            h._node("n1", 7).clock.add(t + k, t + k + 1_000_000, t + k + 1_000_001, t + k + 2)
        for k in range(2000):  # junk that must be refused: cut short, another magic or
            kind = sorted(KEYS)[k % 4]  # version, random bytes
            data = bytearray(good[kind])
            if k % 3 == 0:
                data = data[:int(rng.integers(0, len(data)))]
            elif k % 3 == 1:
                data[int(rng.integers(0, 3))] ^= int(rng.integers(1, 256))
            else:
                data = rng.integers(0, 256, int(rng.integers(0, 200)), np.uint8).tobytes()
            deliver(h, kind, bytes(data))
        nan = bytearray(good["blobs"])
        nan[wire.BLOBS_HEAD.size:wire.BLOBS_HEAD.size + 4] = np.float32(np.nan).tobytes()
        deliver(h, "blobs", bytes(nan))
        before = [len(c.samples) for c in caps]
        deliver(h, "blobs", good["blobs"])
        deliver(h, "sets", good["sets"])
    # the good ones after the junk arrive whole, times mapped to the daemon's clock
    assert [len(c.samples) - b for c, b in zip(caps, before, strict=True)] == [2, 1]
    s = caps[0].samples[-1]
    np.testing.assert_array_equal(s.uv, [[10.5, 20.25], [300.0, 40.0]])
    assert abs(s.t_ns - (1000 - 1_000_000)) <= 2
    assert all(np.isfinite(c.uv).all() for cap in caps for c in cap.samples)
    assert h.refused.counts["blobs message that does not decode"] >= 1
    lines = [r for r in caplog.records if "ignoring" in r.getMessage()]
    assert h.bad >= 2001 and 4 <= len(lines) == len(h.refused.counts)
    assert not [r for r in caplog.records if r.exc_info]


def test_made_up_boot_ids_do_not_grow_the_node_table():
    h = hub()
    for boot in range(2000):
        deliver(h, "announce", json.dumps({"node": f"n{boot}", "boot": boot,
                                           "cameras": [f"x{boot}"]}).encode())
        for node in h.nodes.values():
            node.last_heard -= 10  # silent since: forgettable
    assert len(h.nodes) <= 64 and len(h._warned) <= 256
