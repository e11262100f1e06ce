"""The VRPN server's inputs fuzzed: a UDP call-back request and a TCP client's stream
(cookie, descriptions, pings), random bytes and real ones changed or cut, handled as the
server thread handles them. None escapes, none logs a traceback, and each kind of bad
input is one line (benchmarks/fuzz_parsers.py --only vrpn runs 10^5 of them)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import fuzz_parsers  # noqa: E402


def test_junk_at_the_vrpn_server_escapes_nothing_and_logs_a_line_per_kind():
    fig = fuzz_parsers.run_parser("vrpn", 5000, 1, seed=7)
    assert fig["inputs"] == 5000 and fig["unhandled"] == 0, fig["unhandled_kinds"]
    assert fig["tracebacks"] == 0 and fig["max_lines_per_kind"] == 1
    assert fig["kinds_logged"] >= 2  # bad datagrams and bad streams were both seen


def test_a_good_client_stream_is_understood():
    """The harness's good stream is what a client sends: it names its sender and the ping
    type, gives its UDP port and pings; the server answers the ping (so the fuzzing starts
    from inputs that go past the first check)."""
    from daemon.publish import vrpn as vr
    from daemon.tracking.rigid import BodyDef

    good, _junk, _call = fuzz_parsers.vrpn()
    pub = vr.VrpnPublisher([BodyDef("b", 1, np.eye(3) * 0.05, np.zeros(3))], port=0)
    feed = fuzz_parsers._FeedSocket()
    c = vr._Client(feed, ("127.0.0.1", 40000))
    feed.data = good[2]
    pub._read(c)
    assert c.connected and c.senders == {0: "b"} and c.types == {0: vr.PING}
    assert c.udp == ("127.0.0.1", 40001) and c.pings == 1 and pub.pongs == 1
