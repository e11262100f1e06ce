"""What mocapd parses from an autopilot (HEARTBEAT, TIMESYNC, anything else) under random
and corrupted bytes: nothing raises, junk is counted and logged once per kind, and the
real messages hidden in the junk are still heard (issue 30)."""

from __future__ import annotations

import logging

from hypothesis import given, settings
from hypothesis import strategies as st
from pymavlink.dialects.v20 import common

from daemon.publish.mavlink_link import MavlinkLink

AP = common.MAVLink(None, srcSystem=1, srcComponent=1)
HEARTBEAT = AP.heartbeat_encode(2, 3, 0, 0, 4).pack(AP)  # a quadrotor, ArduPilot
TIMESYNC_ASK = AP.timesync_encode(0, 123456789).pack(AP)
TIMESYNC_ANSWER = AP.timesync_encode(99, 5).pack(AP)
GOOD = [HEARTBEAT, TIMESYNC_ASK, TIMESYNC_ANSWER]


def _link() -> MavlinkLink:
    link = MavlinkLink("udpout:127.0.0.1:9", 57600, 1, 197)
    link.sent = []
    link.send = link.sent.append  # what it would write (no port is opened)
    return link


@st.composite
def corrupted(draw) -> bytes:
    """A real message with a few bytes changed, cut short or with junk around it."""
    data = bytearray(draw(st.sampled_from(GOOD)))
    for _ in range(draw(st.integers(0, 4))):
        data[draw(st.integers(0, len(data) - 1))] = draw(st.integers(0, 255))
    data = data[:draw(st.integers(0, len(data)))]
    return draw(st.binary(max_size=20)) + bytes(data) + draw(st.binary(max_size=20))


_LINK = _link()


@settings(max_examples=500, deadline=None)
@given(chunks=st.lists(st.one_of(st.binary(max_size=300), corrupted(),
                                 st.sampled_from(GOOD)), max_size=6))
def test_any_bytes_from_the_autopilot_are_parsed_without_raising(chunks):
    before = _LINK.received
    for data in chunks:
        _LINK.receive(data)
    # only real messages count as received: never more than the real messages sent
    assert _LINK.received - before <= sum(len(c) // len(TIMESYNC_ANSWER) + 1 for c in chunks)


def test_real_messages_inside_junk_are_heard_and_junk_is_logged_once_per_kind(caplog):
    link = _link()
    junk = bytes(range(256)) * 4 + b"\xfd" * 50 + b"\xfe\x09" * 30
    broken = bytearray(HEARTBEAT)
    broken[-1] ^= 0xFF  # a bad checksum
    with caplog.at_level(logging.INFO, "mocapd"):
        for _ in range(200):
            link.receive(junk)
            link.receive(bytes(broken))
        # the junk ends inside what reads as a long message's header: the parser waits for
        # its end before it finds its feet again, as any MAVLink parser does; the
        # autopilot's heartbeats are heard within a few of them
        beats = 0
        while link.heartbeats_received == 0 and beats < 30:
            link.receive(HEARTBEAT + junk[:7] if beats % 2 else HEARTBEAT)
            beats += 1
        link.receive(TIMESYNC_ASK[:9])  # a message split over two reads
        link.receive(TIMESYNC_ASK[9:])
    assert link.autopilot is not None and link.autopilot["type"] == "quadrotor"
    assert link.heartbeats_received == 1 and beats < 30
    answers = [m for m in link.sent if m.get_type() == "TIMESYNC"]
    assert len(answers) == 1 and answers[0].ts1 == 123456789  # our answer to its request
    assert link.received == 2
    assert sum(link.bad.counts.values()) >= 400  # every broken heartbeat at least
    lines = [r for r in caplog.records if "ignoring" in r.getMessage()]
    assert 1 <= len(lines) == len(link.bad.counts)
    assert not [r for r in caplog.records if r.exc_info]
