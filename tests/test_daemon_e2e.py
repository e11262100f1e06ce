"""`mocapd start --sim` end to end: UDP, serial and MAVLink out, control socket, signals."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

from daemon.config.mocapd import SimConfig
from daemon.publish import packet
from daemon.synthetic.scene import SimScene

ROOT = Path(__file__).resolve().parents[1]
SIM = dict(cameras=6, bodies=2, markers_per_body=4, fps=120.0, noise_px=0.2, seed=11)


def _sim_toml(**extra) -> str:
    sim = {**SIM, **extra}
    return "[sim]\n" + "".join(f"{k} = {json.dumps(v)}\n" for k, v in sim.items())


def _udp_socket():
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    s.setblocking(False)
    return s


def _drain_udp(sock, into: list) -> None:
    while True:
        try:
            data = sock.recv(65536)
        except BlockingIOError:
            return
        into.append((time.monotonic_ns(), packet.decode(data)))


def _drain_fd(fd, buf: bytearray) -> None:
    import select

    while select.select([fd], [], [], 0)[0]:
        buf += os.read(fd, 65536)


def _start(args, env_extra=None):
    env = dict(os.environ, PYTHONPATH=str(ROOT), **(env_extra or {}))
    return subprocess.Popen([sys.executable, "-m", "daemon.cli", "start", *map(str, args)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env, cwd=ROOT)


def _read_notes(sock):
    """systemd's notify messages, read on a thread until finish() is called: a Unix datagram
    socket queues only a few (net.unix.max_dgram_qlen, 10 by default) and the daemon drops
    one that would block (daemon.process.notify), so they must be read while the test does other
    things (status, recordings) or a RELOADING=1 sent then is lost."""
    notes: list[str] = []
    stop = threading.Event()
    sock.settimeout(0.05)

    def run():
        while True:
            stopping = stop.is_set()
            try:
                while True:
                    notes.append(sock.recv(4096).decode())
            except (TimeoutError, BlockingIOError):
                pass
            if stopping:
                return

    thread = threading.Thread(target=run, daemon=True)
    thread.start()

    def finish():
        stop.set()
        thread.join(10)

    return notes, finish


def _wait_for(cond, timeout_s: float, what: str, proc=None, poll=None) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if poll:
            poll()
        if cond():
            return
        if proc is not None and proc.poll() is not None:
            raise AssertionError(f"mocapd exited early: {proc.stderr.read().decode()}")
        time.sleep(0.02)
    raise AssertionError(f"timed out waiting for {what}")


def test_live_daemon_outputs_control_reload_and_stop(tmp_path, mocapd_cli):
    """One daemon: poses over UDP (checked against the simulator's truth), COBS frames on a
    pty, MAVLink on another, status and recording over the control socket, a SIGHUP that
    adds an output, a SIGTERM that stops it cleanly."""
    rx, rx2 = _udp_socket(), _udp_socket()
    ser_m, ser_s = os.openpty()
    mav_m, mav_s = os.openpty()
    notify = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    notify.bind(str(tmp_path / "notify"))
    rt = tmp_path / "rt"
    cfg = tmp_path / "mocapd.toml"
    base = _sim_toml() + (f'[[udp]]\naddress = "127.0.0.1:{rx.getsockname()[1]}"\n'
                          f'[[mavlink]]\ndevice = "{os.ttyname(mav_s)}"\nbody = 1\n'
                          'message = "att_pos_mocap"\nrate_hz = 30\n')
    cfg.write_text(base)
    proc = _start(["--config", cfg, "--serial", f"{os.ttyname(ser_s)}:115200",
                   "--runtime-dir", rt, "--json", tmp_path / "run.json"],
                  {"NOTIFY_SOCKET": str(tmp_path / "notify"), "WATCHDOG_USEC": "1000000"})
    got, got2, ser, mav = [], [], bytearray(), bytearray()
    notes, finish_notes = _read_notes(notify)

    def poll():
        _drain_udp(rx, got)
        _drain_udp(rx2, got2)
        _drain_fd(ser_m, ser)
        _drain_fd(mav_m, mav)

    try:
        _wait_for(lambda: len(got) > 60, 180, "UDP packets", proc, poll)
        assert "READY=1" in notes
        # status over the control socket (mode 0600)
        assert (rt / "mocapd.sock").stat().st_mode & 0o777 == 0o600
        r = mocapd_cli("status", "--runtime-dir", rt, "--json", tmp_path / "status.json")
        assert r.code == 0, r.err
        st = json.loads((tmp_path / "status.json").read_text())
        assert len(st["cameras"]) == 6
        # every camera delivering: its count rises between two reads (a rate over the
        # last second is the machine's figure: a loaded one stalls a capture thread)
        assert all(c["frames"] > 0 and c["rate_hz"] >= 0 for c in st["cameras"])
        first = {c["name"]: c["frames"] for c in st["cameras"]}
        assert st["bodies_tracked"] == 2
        assert mocapd_cli("record", tmp_path / "rec.mcrec", "--runtime-dir", rt).code == 0
        time.sleep(0.3)
        r = mocapd_cli("record", "--stop", "--runtime-dir", rt)
        assert r.code == 0 and "recorded" in r.out
        # another kind of file is refused in one line, and nothing is recorded
        r = mocapd_cli("record", tmp_path / "rec.txt", "--runtime-dir", rt)
        assert r.code == 2 and ".mcrec" in r.err and not (tmp_path / "rec.txt").exists()
        # poses and markers as MCAP (Foxglove's schemas) while the stream goes on
        assert mocapd_cli("record", tmp_path / "live.mcap", "--runtime-dir", rt).code == 0
        time.sleep(0.5)
        assert mocapd_cli("record", "--stop", "--runtime-dir", rt).code == 0
        _check_live_mcap(tmp_path / "live.mcap", st["bodies"])
        r = mocapd_cli("status", "--runtime-dir", rt, "--json", tmp_path / "status2.json")
        assert r.code == 0, r.err
        st2 = json.loads((tmp_path / "status2.json").read_text())
        later = st2["cameras"]
        assert all(c["frames"] > first[c["name"]] for c in later), (first, later)
        # the simulator's scorers ran between sets, their CPU counted apart (bench_nodes)
        assert st2["scorers_cpu_s"] > st["scorers_cpu_s"] >= 0
        # SIGHUP: a second UDP output appears without stopping the stream
        cfg.write_text(base + f'[[udp]]\naddress = "127.0.0.1:{rx2.getsockname()[1]}"\n')
        n_before = len(got)
        proc.send_signal(signal.SIGHUP)
        _wait_for(lambda: len(got2) > 20, 60, "packets on the reloaded output", proc, poll)
        assert "RELOADING=1" in notes
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=60)
        poll()
    finally:
        if proc.poll() is None:
            proc.kill()
        for fd in (ser_m, ser_s, mav_m, mav_s):
            os.close(fd)
        finish_notes()  # its last look comes after the daemon has exited
    assert proc.returncode == 0, err.decode()
    assert "STOPPING=1" in notes
    assert "WATCHDOG=1" in notes  # at half WATCHDOG_USEC from the frame loop
    assert any(n.startswith("STATUS=") and "fps" in n for n in notes)
    assert not (rt / "mocapd.sock").exists()
    assert len(got) > n_before

    # UDP: frames in order, poses where the simulator put the bodies at each packet's time
    fig = json.loads((tmp_path / "run.json").read_text())
    scene = SimScene(SimConfig(**SIM))
    scene.t0_ns = fig["truth"]["scene_t0_ns"]  # when the run's scene started
    frames = np.array([p.frame for _, p in got])
    assert np.all(np.diff(frames) > 0)
    errors, valid = [], 0
    for _, p in got[10:]:
        _, true_t = scene.body_poses_at(p.t_ns)
        for k, b in enumerate(scene.bodies_truth):
            i = np.flatnonzero(p.ids == b.id)[0]
            if p.valid[i]:
                valid += 1
                errors.append(np.linalg.norm(p.position[i] - true_t[k]))
    assert valid >= 0.85 * 2 * (len(got) - 10)  # 4-marker bodies start with all 4 seen
    assert np.sqrt(np.mean(np.square(errors))) < 0.002  # ~0.6 mm expected at 0.2 px
    # the daemon's own latency field (this loop polls too slowly to time arrivals; the
    # benchmark measures the receiver side); loose bounds for a shared CI machine
    latency_ms = np.array([p.latency_ns * 1e-6 for _, p in got])
    assert 0 < np.median(latency_ms) < 20

    # serial: every frame decodes, CRC good, the same poses as UDP
    frames_ser = bytes(ser).split(b"\x00")[:-1]
    assert len(frames_ser) > 20
    decoded = [packet.decode(packet.read_serial_frame(f)) for f in frames_ser[1:]]
    by_frame = {p.frame: p for _, p in got}
    same = [p for p in decoded if p.frame in by_frame]
    assert same and np.allclose(same[0].position, by_frame[same[0].frame].position,
                                equal_nan=True)

    # MAVLink: ATT_POS_MOCAP in NED, ~30 Hz
    from pymavlink.dialects.v20 import common as mavlink2

    msgs = mavlink2.MAVLink(None).parse_buffer(bytes(mav)) or []
    poses = [m for m in msgs if m.get_type() == "ATT_POS_MOCAP"]
    assert len(poses) > 10 and {m.get_type() for m in msgs} <= {"ATT_POS_MOCAP", "HEARTBEAT"}
    assert any(m.get_type() == "HEARTBEAT" for m in msgs)
    assert all(m.z < 0 for m in poses)  # bodies are above the floor: up is -z in NED

    from calibkit.core.recording import load_observations

    obs, _ = load_observations(tmp_path / "rec.mcrec")
    assert len(obs.frames()) > 10 and set(np.unique(obs.camera)) == set(range(6))
    assert fig["frames"] > 60


def test_camera_dropout_and_a_consumer_that_stops_reading(tmp_path):
    """cam2 disconnects for 0.4 s and is reopened; a serial consumer never reads. Tracking
    goes on, UDP keeps flowing, the bodies stay tracked. The daemon runs until its UDP
    packets have passed 1.5 s of the scene (however long a loaded machine takes), then is
    stopped."""
    rx = _udp_socket()
    ser_m, ser_s = os.openpty()
    os.set_blocking(ser_s, False)
    try:  # the consumer has stopped reading: its buffer is already full
        while True:
            os.write(ser_s, b"x" * 4096)
    except BlockingIOError:
        pass
    cfg = tmp_path / "mocapd.toml"
    # the cameras open together here, so that frame counts show what cam2 missed
    cfg.write_text(_sim_toml(drop_camera="cam2", drop_from_s=0.3, drop_for_s=0.4,
                             open_spread_s=0.0)
                   + f'[[serial]]\ndevice = "{os.ttyname(ser_s)}"\nrate_hz = 0\nbaud = 230400\n')
    got = []
    proc = _start(["--config", cfg, "--udp", f"127.0.0.1:{rx.getsockname()[1]}",
                   "--duration", 120, "--runtime-dir", tmp_path / "rt",
                   "--json", tmp_path / "run.json"])
    try:
        _wait_for(lambda: got and got[-1][1].frame > 180, 240, "UDP packets past frame 180",
                  proc, lambda: _drain_udp(rx, got))
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=30)
        _drain_udp(rx, got)
    finally:
        if proc.poll() is None:
            proc.kill()
        os.close(ser_m)
        os.close(ser_s)
    assert proc.returncode == 0, err.decode()
    fig = json.loads((tmp_path / "run.json").read_text())
    cams = {c["name"]: c for c in fig["cameras"]}
    assert cams["cam2"]["failures"] >= 1 and cams["cam2"]["connected"]
    # cam2 took no frame while it was away (0.3-0.7 s after its first one: 48 triggers at 120
    # fps); a frame that a capture thread late on a loaded machine never read counts as taken
    # (a gap in its camera's counter), so the cameras are compared on what they took. A
    # camera's count starts at the first frame its thread read, which on a loaded machine (two
    # CPU hogs beside the suite) came up to 22 frames after another's: cam2 against the camera
    # that took most, by at least 20 of the 48
    taken = {n: c["frames"] + c["frame_gaps"] for n, c in cams.items()}
    assert taken["cam2"] < max(v for n, v in taken.items() if n != "cam2") - 20, cams
    assert "cam2: camera disconnected" in err.decode()
    serial_out = [o for o in fig["outputs"] if o["name"].startswith("serial")][0]
    assert serial_out["errors"] >= 1 and "send failed" in serial_out["last_error"]
    # UDP carried every frame tracked (the blocked serial line held up nothing), while
    # cam2 was away (sets 36 to 84 at 120 fps) and after. A loaded machine's frame loop
    # skips sets to stay current (as many as 70 of 190 at load 20), so how many frames
    # were tracked is a speed, measured in benchmarks/, not here.
    udp_frames = np.array([p.frame for _, p in got])
    assert len(udp_frames) >= 0.9 * fig["frames"] > 0
    assert np.any((udp_frames > 40) & (udp_frames < 80)) and udp_frames.max() > 100
    truth = fig["truth"]
    assert truth["body_swaps"] == 0
    # no marker track swapped while every set was tracked; a loaded machine's frame loop
    # skips sets, and across the wider jump one swap was seen (load 7, two CPU hogs and
    # labelling benchmarks beside the suite): that is the load's, not the dropout's
    mux = fig.get("multiplexer") or {}
    skipped = (mux.get("skipped_behind") or 0) + (mux.get("overflow") or 0)
    assert truth["track_swaps"] <= (0 if skipped == 0 else 2), (truth["track_swaps"], mux)
    # 0.96-1.0 on a quiet machine; 0.78 at load 20, where skipped sets are wider jumps
    assert all(b["valid_fraction"] > 0.7 for b in truth["bodies"].values())


def test_fast_sim_run_writes_pose_errors(tmp_path, mocapd_cli):
    """The `calibkit demo` path: --sim --rig --frames --json, no real-time pacing."""
    from calibkit.synthetic import sim

    rig = sim.make_rig(6, 4.0, seed=2)
    rig.save(tmp_path / "rig.toml")
    # (the cameras open up to 0.3 s apart and are paired by the multiplexer, as in a live
    # run: bodies are short of cameras in the first ~70 sets, which 2000 sets outweigh)
    r = mocapd_cli("start", "--sim", "--rig", tmp_path / "rig.toml", "--fast", "--frames", 2000,
                   "--sim-bodies", 3, "--noise-px", 0.2, "--json", tmp_path / "f.json",
                   "--runtime-dir", tmp_path / "rt")
    assert r.code == 0, r.err
    fig = json.loads((tmp_path / "f.json").read_text())
    assert fig["frames"] == 2000
    t = fig["truth"]
    assert len(t["bodies"]) == 3
    for b in t["bodies"].values():
        assert b["valid_fraction"] > 0.95
        assert b["position_error_mm_rms"] < 1.5
        assert b["orientation_error_deg_rms"] < 1.5
    assert t["track_swaps"] == 0 and t["body_swaps"] == 0
    assert "pos_err_mm_rms" in r.out
    # no --truth-rig: the rig tracked with made the blobs too, and the figures say so
    assert "perfect calibration" in t["tracking_rig"] and "perfect calibration" in r.out
    # the bodies were defined live, as a user would, not handed over by the simulator:
    # written as a configuration's tables, each matched to a scene body by its shape, and
    # off the scene's own markers by the tracking noise (0.2 px: a fraction of a mm)
    live = fig["bodies_defined_live"]
    assert [b["markers"] for b in live["bodies"]] == [4, 4, 4]
    assert "defined live at the start" in r.out
    from daemon.config.mocapd import load_config
    from daemon.synthetic.evaluator import match_bodies
    from daemon.synthetic.scene import SimScene

    defs = load_config(live["file"]).bodies
    assert [b.name for b in defs] == ["body0", "body1", "body2"]
    scene = SimScene(SimConfig(bodies=3, noise_px=0.2), rig, n_frames=2000)
    matched = list(match_bodies([b.markers_body for b in scene.bodies_truth],
                                [b.markers for b in defs]))
    assert sorted(m[0] for m in matched) == [0, 1, 2]
    assert all(0 < m[5] < 0.001 for m in matched)
    assert {b["defined_as"] for b in t["bodies"].values()} == {"body0", "body1", "body2"}
    assert all(b["definition_error_mm_rms"] < 1.0 for b in t["bodies"].values())


def test_control_commands_without_a_daemon(tmp_path, mocapd_cli):
    for args in (["status"], ["stop"], ["record", tmp_path / "x.mcrec"]):
        r = mocapd_cli(*args, "--runtime-dir", tmp_path)
        assert r.code == 2 and "no mocapd running" in r.err
        assert len(r.err.strip().splitlines()) == 1


def test_install_unit(tmp_path, mocapd_cli):
    (tmp_path / "mocapd.toml").write_text(_sim_toml())
    out = tmp_path / "mocapd.service"
    r = mocapd_cli("install-unit", "--config", tmp_path / "mocapd.toml", "--out", out)
    assert r.code == 0, r.err
    # it builds the kernels ahead of the first start (cached already here: a few seconds)
    from daemon.commands.kernels_cmd import STEPS

    n = len(STEPS)  # every step of `mocapd build-kernels`, the last one finished
    assert f"[{n}/{n}] {STEPS[-1][0]}:" in r.out and "kernels built in" in r.out
    assert r.out.splitlines()[-1].startswith("then: ")
    text = out.read_text()
    assert "Type=notify" in text and "ExecReload=/bin/kill -HUP $MAINPID" in text
    assert f"--config {tmp_path / 'mocapd.toml'}" in text and "WatchdogSec=5" in text
    assert "WantedBy=multi-user.target" in text and "Nice=-10" in text  # a system unit
    user = tmp_path / ".config/systemd/user/mocapd.service"
    r = mocapd_cli("install-unit", "--config", tmp_path / "mocapd.toml", "--out", user,
                   "--no-build-kernels")
    assert r.code == 0 and "kernels built" not in r.out
    assert "Nice=" not in user.read_text()  # a user manager may not raise priority
    r = mocapd_cli("install-unit", "--config", tmp_path / "missing.toml", "--out", out)
    assert r.code == 2


def test_replay_a_recording(tmp_path, mocapd_cli):
    """A recording (as `mocapd record` writes) played back as fast as possible, with the
    bodies defined in the configuration."""
    from calibkit.core.recording import save_observations
    from calibkit.synthetic import sim

    rig = sim.make_rig(6, 4.0, seed=8)
    rig.save(tmp_path / "rig.toml")
    truth, bodies = sim.rigid_body_motion(2, 150, 100.0, 4.0, 4, seed=9)
    obs = sim.observe(rig, truth, noise_px=0.2, fps=100.0, seed=10)
    save_observations(tmp_path / "rec.mcrec", obs, truth, rig)
    text = "".join(f'[[rigid_body]]\nname = "{b.name}"\nid = {b.id}\nmarkers = '
                   f"{np.round(b.markers_body, 9).tolist()}\n" for b in bodies)
    (tmp_path / "mocapd.toml").write_text(text)
    r = mocapd_cli("start", "--config", tmp_path / "mocapd.toml", "--rig", tmp_path / "rig.toml",
                   "--replay", tmp_path / "rec.mcrec", "--fast", "--json", tmp_path / "f.json",
                   "--runtime-dir", tmp_path / "rt")
    assert r.code == 0, r.err
    fig = json.loads((tmp_path / "f.json").read_text())
    assert fig["frames"] == 150
    assert fig["markers_tracked_median"] == 8
    assert all(v > 0.95 for v in fig["bodies_valid_fraction"].values())
    # a recording whose cameras the rig does not have: one line, exit 2
    obs.camera_names = tuple(f"side{i}" for i in range(len(obs.camera_names)))
    save_observations(tmp_path / "bad.mcrec", obs, truth, None)
    r = mocapd_cli("start", "--rig", tmp_path / "rig.toml", "--replay", tmp_path / "bad.mcrec",
                   "--runtime-dir", tmp_path / "rt")
    assert r.code == 2 and "not in the rig" in r.err
    assert len(r.err.strip().splitlines()) == 1


def test_live_cameras_with_a_missing_plugin(tmp_path, mocapd_cli):
    """Cameras from the configuration: one reads image files through detection, one needs
    pypylon (not installed here): it is reported and skipped, the other runs."""
    import cv2

    from calibkit.synthetic import sim

    rig = sim.make_rig(3, 4.0, seed=8)
    rig.save(tmp_path / "rig.toml")
    xyz = sim.static_markers(6, 1, seed=3).xyz
    for c in range(2):
        folder = tmp_path / f"cam{c}"
        folder.mkdir()
        for i in range(5):
            cv2.imwrite(str(folder / f"{i:03d}.png"), sim.render_frame(rig[c], xyz, seed=i)[0])
    (tmp_path / "mocapd.toml").write_text(
        'rig = "rig.toml"\n[pipeline]\nfps = 30\n'
        '[[camera]]\nname = "cam0"\nsource = "cam0"\nfps = 30\n'
        '[[camera]]\nname = "cam1"\nsource = "cam1"\nfps = 30\n'
        '[[camera]]\nname = "cam2"\nsource = "basler:12345"\n')
    r = mocapd_cli("start", "--config", tmp_path / "mocapd.toml", "--duration", 60,
                   "--json", tmp_path / "f.json", "--runtime-dir", tmp_path / "rt")
    assert r.code == 0, r.err
    assert "cam2: skipped: plugin basler (needs pypylon) is not installed" in r.err
    fig = json.loads((tmp_path / "f.json").read_text())
    cams = {c["name"]: c for c in fig["cameras"]}
    assert cams["cam0"]["frames"] == 5 and cams["cam1"]["frames"] == 5
    assert cams["cam2"]["frames"] == 0
    assert "every source has ended" in r.err  # it stopped by itself, long before 60 s


def test_greedy_multiplexer(tmp_path, mocapd_cli):
    """Greedy mode: a frame set per camera report, the other cameras' blobs moved to its
    time. The bodies stay tracked, within a few millimetres, without swaps. Run with
    --fast: the simulated cameras in virtual time through the same multiplexer, so what is
    checked is the pairing and the tracking, not how fast this machine is (a loaded
    machine's frame loop skips sets: docs/daemon.md)."""
    cfg = tmp_path / "mocapd.toml"
    cfg.write_text(_sim_toml(cameras=4, bodies=2, fps=60.0))
    r = mocapd_cli("start", "--config", cfg, "--mode", "greedy", "--fast", "--duration", 1.5,
                   "--json", tmp_path / "g.json", "--runtime-dir", tmp_path / "rt")
    assert r.code == 0, r.err
    fig = json.loads((tmp_path / "g.json").read_text())
    # more sets than frames in 1.5 s of the cameras' time: one per camera report
    assert fig["frames"] > 60 * 1.5 * 1.5
    assert fig["multiplexer"]["incomplete_sets"] == 0  # greedy sets hold every camera
    t = fig["truth"]
    assert t["track_swaps"] == 0 and t["body_swaps"] == 0
    for b in t["bodies"].values():  # four cameras only: bodies are sometimes unseen
        assert b["valid_fraction"] > 0.6
        assert b["position_error_mm_rms"] < 5.0


def test_greedy_multiplexer_with_unsynchronised_cameras(tmp_path, mocapd_cli):
    """Cameras whose clocks are up to half a frame apart (8 ms at 60 fps): greedy sets move
    the other cameras' blobs to the newest camera's time along their 2D motion. Scored
    against the truth at each set's own time. Without the extrapolation this scene gave
    3.4 mm RMS, bodies valid in 15-38 % of the sets and 8 track swaps; with it, over ten
    seeds, 0.9-1.2 mm and no swap (the triggered multiplexer: 0.8-1.7 mm), leaving out
    the few gross errors; over every pose, with the cameras' own clocks, 1.1-1.6 mm."""
    cfg = tmp_path / "mocapd.toml"
    cfg.write_text(_sim_toml(cameras=4, bodies=2, fps=60.0, unsync_ms=8.0))
    r = mocapd_cli("start", "--config", cfg, "--mode", "greedy", "--fast", "--duration", 2.0,
                   "--json", tmp_path / "g.json", "--runtime-dir", tmp_path / "rt")
    assert r.code == 0, r.err
    t = json.loads((tmp_path / "g.json").read_text())["truth"]
    assert t["body_swaps"] == 0 and t["track_swaps"] == 0
    for b in t["bodies"].values():  # four cameras: bodies are sometimes unseen
        assert b["valid_fraction"] > 0.6
        # a few poses more than 2 cm / 5 degrees off (where the scene turns back); the RMS
        # over every pose counts them, so they are bounded apart
        assert b["gross_error_frames"] <= 0.03 * b["valid_fraction"] * t["frames_scored"]
        assert b["position_error_mm_rms_without_gross"] < 1.8
        assert b["position_error_mm_rms"] < 3.0
    bad = tmp_path / "bad.toml"
    bad.write_text(_sim_toml(fps=60.0, unsync_ms=20.0))
    r = mocapd_cli("start", "--config", bad, "--duration", 1, "--runtime-dir", tmp_path / "rt")
    assert r.code == 2 and "sim.unsync_ms" in r.err


def test_late_opener_and_a_reconnecting_camera_live(tmp_path):
    """The daemon on simulated cameras that open up to 2 s apart, each counting from its
    own start on a clock drifting up to 50 ppm, one of them reconnecting (a new counter and
    clock epoch): no frame set mixes instants (the simulator's truth), and the late opener
    and the reconnected camera are tracked with within 0.5 s of delivering frames (about
    0.1 s and 0.22 s here: the clock's settling, and the 0.2 s between reopening tries)."""
    from daemon.config.mocapd import Config
    from daemon.service.daemon import Daemon

    sim = SimConfig(cameras=5, bodies=2, fps=100.0, seed=11, open_spread_s=2.0,
                    clock_drift_ppm=50.0, drop_camera="cam1", drop_from_s=0.7, drop_for_s=0.3)
    # (cam1 opens 1.28 s in: it is away 2.0-2.3 s, 0.7 s after its first frame)
    daemon = Daemon(Config(sim=sim, fps=sim.fps, runtime_dir=tmp_path / "rt"))
    used = []  # per frame: its time, and which cameras' blobs the tracks took

    def progress(_):
        r = daemon.pipeline.last_result
        if r is not None and (not used or used[-1][0] != r.frame):
            cams = np.unique(r.camera[r.tracks.blobs[r.tracks.blobs >= 0]])
            used.append((r.frame, r.t_ns, set(cams.tolist())))

    fig = daemon.run(duration_s=3.3, progress=progress)
    scene = daemon.scene
    t = fig["truth"]
    # live, the capture threads' timing is the machine's, busy or not: a clock settles
    # only on frames that arrived on time (tests/test_multiplexer.py stalls a thread as
    # its camera opens), so not one set may mix instants
    assert t["sets_checked_for_instants"] > 100  # of 330 (a loaded machine skips some)
    assert t["sets_mixing_instants"] == 0
    assert t["samples_not_in_ledger"] == 0

    def tracked_after(camera, since_ns):
        return min(tn for _, tn, cams in used if tn > since_ns and camera in cams) - since_ns

    late = int(np.argmax(scene.open_delay_ns))
    assert scene.open_delay_ns[late] == 2e9
    assert tracked_after(late, scene.t0_ns + scene.open_delay_ns[late]) < 0.5e9
    back = scene.t0_ns + round((scene.first_trigger[1] / sim.fps + sim.drop_from_s
                                + sim.drop_for_s) * 1e9)  # cam1 is back
    assert tracked_after(1, back) < 0.5e9
    cams = {c["name"]: c for c in fig["cameras"]}
    assert cams["cam1"]["failures"] >= 1 and cams["cam1"]["clock"]["resets"] >= 1
    assert all(c["clock"]["source"] == "device time" for c in cams.values())
    # a sample later than its set's deadline is left out of it; a wrong clock or deadline
    # would make most of them late, a loaded machine's stalled capture threads a few (10 of
    # about 1500 beside the hogs; 45 of 987 in run 24, the frame loop 30 % behind)
    delivered = sum(c["frames"] for c in cams.values())
    assert fig["multiplexer"]["late_samples"] < 0.1 * delivered, (fig["multiplexer"],
                                                                    delivered)


def _check_live_mcap(path, bodies) -> None:
    """Both bodies posed in the recorded frames, each pose in a frame that has its markers,
    on the wall clock, with unit quaternions; markers held by bodies marked as such. (How
    often a body is posed is the tracking tests' business: at load 8 the bodies here were
    posed in 13 of 31 frames, their sets skipped or incomplete.)"""
    from test_mcap import read_mcap

    topics, _ = read_mcap(path)
    frames = len(topics["/mocap/markers"])
    assert frames > 20  # 0.5 s at 100 fps, on a loaded machine
    marker_times = {t for t, _, _ in topics["/mocap/markers"]}
    for b in bodies:
        msgs = topics[f"/mocap/{b['name']}/pose"]
        assert len(msgs) >= 5
        assert {t for t, _, _ in msgs} <= marker_times
        q = np.array([[m["pose"]["orientation"][k] for k in "xyzw"] for _, _, m in msgs])
        np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-6)
        t_s = np.array([t for t, _, _ in msgs]) / 1e9
        assert abs(t_s[-1] - time.time()) < 30  # capture times on the wall clock
    held = [s["color"]["g"] > 0.7 for _, _, m in topics["/mocap/markers"]
            for s in m["entities"][0]["spheres"]]
    assert any(held)


def test_sim_without_scoring_runs_the_daemon_alone(tmp_path, mocapd_cli):
    """`[sim] score = false`: the simulator feeds the daemon, nothing compares with the
    truth (what a latency measurement of the daemon's own cost wants)."""
    cfg = tmp_path / "mocapd.toml"
    cfg.write_text("[sim]\ncameras = 4\nbodies = 2\nscore = false\n")
    # 1 s: the cameras open up to 0.3 s apart, paired by the multiplexer as in a live run
    r = mocapd_cli("start", "--config", cfg, "--fast", "--frames", 240, "--json",
                   tmp_path / "f.json", "--runtime-dir", tmp_path / "rt")
    assert r.code == 0, r.err
    fig = json.loads((tmp_path / "f.json").read_text())
    assert fig["frames"] == 240 and "truth" not in fig
    assert all(v > 0.5 for v in fig["bodies_valid_fraction"].values())
