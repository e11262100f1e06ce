"""Reloads of random configurations, valid and not, into a daemon that is tracking.

Issue 30: a reload is a transaction. Each example writes a configuration made of parts
whose validity the test knows from how it built them (rigid bodies from the ones the
daemon learned, UDP outputs to loopback readers or to a port that cannot be, tracker
gates in range or not, and sometimes one fault: broken TOML, an unknown key, a rig file
that is not there), reloads, and checks: a valid file takes whole (the bodies, outputs
and gates it names are the running ones), an invalid one changes nothing, and either way
the stream goes on and `status` answers.
"""

from __future__ import annotations

import socket

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from test_reload import _frames_after, _run_with

pytestmark = pytest.mark.slow
SIM = "[sim]\ncameras = 4\nbodies = 2\nfps = 100.0\nseed = 7\ndefine_bodies = false\n"
FAULTS = {"broken TOML": "[[udp]\n", "an unknown key": "bogus = 1\n",
          "a missing rig": 'rig = "/nonexistent/rig.toml"\n'}


@pytest.fixture(scope="module")
def live(tmp_path_factory):
    """A daemon tracking two simulated bodies, the [[rigid_body]] tables it learned for
    them, and two loopback UDP readers."""
    folder = tmp_path_factory.mktemp("reload_property")
    daemon, cfg_path, thread = _run_with(folder, SIM.replace("define_bodies = false\n", ""),
                                         duration_s=3600.0)
    rt = folder / "rt"
    learned = (rt / "sim-bodies.toml").read_text()
    tables = ["[[rigid_body]]" + t for t in learned.split("[[rigid_body]]")[1:]]
    assert len(tables) == 2
    readers = [socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in range(2)]
    for r in readers:
        r.bind(("127.0.0.1", 0))
    ports = [r.getsockname()[1] for r in readers]
    yield daemon, cfg_path, tables, ports
    daemon.handle({"cmd": "stop"})
    thread.join(60)
    for r in readers:
        r.close()
    assert not thread.is_alive()


configs = st.fixed_dictionaries({
    "bodies": st.lists(st.sampled_from([0, 1]), unique=True, max_size=2),
    "udp": st.lists(st.sampled_from(["reader 0", "reader 1", "port 99999"]), unique=True,
                    max_size=2),
    "gate_px": st.one_of(st.none(), st.floats(1.0, 8.0).map(lambda v: round(v, 2)),
                         st.sampled_from([-1.0, "wide"])),
    "fault": st.one_of(st.none(), st.sampled_from(sorted(FAULTS))),
})


def _write(cfg_path, tables, ports, c) -> bool:
    """The configuration `c` in the daemon's file; whether it is valid (known by
    construction, not asked of the daemon's parser)."""
    text = SIM
    for out in c["udp"]:
        port = 99999 if out == "port 99999" else ports[int(out[-1])]
        text += f'\n[[udp]]\naddress = "127.0.0.1:{port}"\n'
    if c["gate_px"] is not None:
        gate = c["gate_px"] if isinstance(c["gate_px"], float) else f'"{c["gate_px"]}"'
        text += f"\n[tracker]\ngate_px = {gate}\n"
    if c["fault"] is not None:
        text = FAULTS[c["fault"]] + text
    text += "\n" + "\n".join(tables[i] for i in sorted(c["bodies"]))
    cfg_path.write_text(text)
    gate_ok = c["gate_px"] is None or isinstance(c["gate_px"], float) and c["gate_px"] > 0
    return gate_ok and "port 99999" not in c["udp"] and c["fault"] is None


def _running(daemon) -> tuple:
    p = daemon.pipeline
    return (sorted(b.name for b in p.rigid.bodies),
            sorted(o.name for o in p.publishers),
            p.tracker.config.gate_px)


@settings(max_examples=30, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(sequence=st.lists(configs, min_size=1, max_size=3))
def test_random_reloads_take_whole_or_not_at_all_while_tracking(live, sequence):
    daemon, cfg_path, tables, ports = live
    for c in sequence:
        before = _running(daemon)
        valid = _write(cfg_path, tables, ports, c)
        assert daemon.reload() is valid, (c, daemon.reload_error)
        _frames_after(daemon, 5)  # the stream goes on either way
        assert daemon.status()["frames"] > 0
        now = _running(daemon)
        if not valid:
            assert now == before, c
            assert daemon.reload_error
            continue
        names = sorted(tables[i].split('name = "')[1].split('"')[0] for i in c["bodies"])
        assert now[0] == names
        assert now[1] == sorted(f"udp:127.0.0.1:{ports[int(o[-1])]}" for o in c["udp"])
        want_gate = c["gate_px"] if c["gate_px"] is not None else \
            type(daemon.pipeline.tracker.config)().gate_px
        assert now[2] == want_gate
