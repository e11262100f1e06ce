"""mocapd.toml: valid files load; every bad one is one line naming file, key and problem."""

from __future__ import annotations

import numpy as np
import pytest

from daemon.config.mocapd import load_config
from daemon.config.outputs import parse_address, parse_serial

GOOD = """
rig = "rig.toml"
markerset = "cmu41"
[pipeline]
mode = "greedy"
fps = 120
[tracker]
gate_px = 4.0
[sim]
cameras = 6
size = [1280, 1024]
person = true
[[rigid_body]]
name = "drone"
id = 3
markers = [[0, 0, 0], [0.12, 0, 0], [0, 0.08, 0.01], [0.05, 0.05, 0.06]]
pivot = [0, 0, -0.02]
smoothing = 0.2
[[udp]]
address = "127.0.0.1:9870"
bodies = [3]
markers = false
[[serial]]
device = "/dev/ttyUSB0"
baud = 57600
[[mavlink]]
device = "/dev/ttyACM0"
body = 3
message = "odometry"
frame = "flu"
"""


def test_a_full_configuration_loads(tmp_path):
    path = tmp_path / "mocapd.toml"
    path.write_text(GOOD)
    cfg = load_config(path)
    assert cfg.rig == tmp_path / "rig.toml"
    assert cfg.mode == "greedy" and cfg.fps == 120
    assert cfg.tracker.gate_px == 4.0
    assert cfg.sim.cameras == 6 and cfg.sim.size == (1280, 1024)
    (body,) = cfg.bodies
    assert body.name == "drone" and body.id == 3 and body.smoothing == 0.2
    np.testing.assert_allclose(body.pivot, [0, 0, -0.02])
    assert cfg.udp[0].host == "127.0.0.1" and cfg.udp[0].port == 9870
    assert cfg.udp[0].bodies == (3,) and cfg.udp[0].markers is False
    assert cfg.markerset.name == "cmu41.toml" and cfg.markerset.exists()  # a shipped set
    assert cfg.sim.person and cfg.sim.person_radius_m == 1.0
    assert cfg.serial[0].baud == 57600
    assert cfg.mavlink[0].message == "odometry" and cfg.mavlink[0].frame == "flu"


def test_address_and_serial_parsing():
    assert parse_address("10.0.0.5:9000") == ("10.0.0.5", 9000)
    assert parse_serial("/dev/ttyUSB0:921600") == ("/dev/ttyUSB0", 921600)
    assert parse_serial("/dev/ttyUSB0") == ("/dev/ttyUSB0", 115200)
    assert parse_serial("socket://host:1234") == ("socket://host:1234", 115200)
    for bad in ("nohost", ":80", "h:0", "h:99999", "h:x"):
        with pytest.raises(ValueError):
            parse_address(bad)


BAD = [
    ("[pipeline]\nmode = 'sometimes'\n", "pipeline.mode", "must be one of"),
    ("[tracker]\ngate_px = 'wide'\n", "tracker.gate_px", "expected a number"),
    ("[tracker]\ngait_px = 3\n", "tracker.gait_px", "unknown key"),
    ("colour = 1\n", "colour", "unknown key"),
    ("[[udp]]\naddress = 'localhost'\n", "udp[0].address", "HOST:PORT"),
    ("[[udp]]\nrate_hz = 5\n", "udp[0].address", "missing"),
    ("[[serial]]\ndevice = '/dev/x'\nbaud = -3\n", "serial[0].baud", "at least"),
    ("[[mavlink]]\ndevice = '/dev/x'\n", "mavlink[0].body", "missing"),
    ("[[mavlink]]\ndevice = '/dev/x'\nbody = 1\nmessage = 'gps'\n", "mavlink[0].message",
     "must be one of"),
    ("[[rigid_body]]\nname = 'a'\nid = 1\nmarkers = [[0, 0, 0], [1, 0, 0]]\n",
     "rigid_body[0] (a).markers", "3 to 32 markers"),
    ("[[rigid_body]]\nname = 'a'\nid = 1\nmarkers = [[0, 0], [1, 0], [0, 1]]\n",
     "rigid_body[0] (a).markers", "expected a list of [x, y, z]"),
    ("[[rigid_body]]\nname = 'a'\nid = 1\nmarkers = [[0,0,0],[0.1,0,0],[0,0.1,0]]\n"
     "[[rigid_body]]\nname = 'b'\nid = 1\nmarkers = [[0,0,0],[0.2,0,0],[0,0.1,0]]\n",
     "rigid_body[1] (b).id", "two rigid bodies have id 1"),
    ("[[rigid_body]]\nname = 'a'\nid = 1\nmarkers = [[0,0,0],[0.001,0,0],[0,0.1,0]]\n",
     "rigid_body[0] (a).markers", "mm apart"),
    ("[sim]\ncameras = 1\n", "sim.cameras", "between 2 and 32"),
    ("[sim]\nsize = 640\n", "sim.size", "[width, height]"),
    ("rig = \n", "", "not valid TOML"),
    ("[[udp]]\naddress = '127.0.0.1:1'\nmarkers = 1\n", "udp[0].markers", "true or false"),
    ("[sim]\nperson = true\nperson_radius_m = 3.0\n", "sim.person_radius_m",
     "inside the volume"),
    ("markerset = 'nowhere.toml'\n", "markerset", "shipped sets: cmu41"),
]


@pytest.mark.parametrize(("text", "key", "problem"), BAD)
def test_bad_configurations_are_one_line_exit_2(tmp_path, start_refused, text, key, problem):
    path = tmp_path / "mocapd.toml"
    path.write_text(text)
    line = start_refused(path)
    assert str(path) in line and key in line and problem in line


def test_missing_files_and_bad_flags(tmp_path, mocapd_cli):
    cases = [
        (["--config", tmp_path / "nope.toml"], "no such configuration file"),
        (["--sim", "--rig", tmp_path / "nope.toml"], "no such rig file"),
        (["--sim", "--udp", "localhost"], "--udp"),
        (["--sim", "--frames", 0], "--frames must be positive"),
        (["--sim", "--mode", "lazy"], "--mode"),
        ([], "no rig given"),
    ]
    for args, text in cases:
        r = mocapd_cli("start", *args, "--runtime-dir", tmp_path / "rt")
        assert r.code == 2, (args, r.err)
        assert len(r.err.strip().splitlines()) == 1 and text in r.err, (args, r.err)
