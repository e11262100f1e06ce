"""The mocapd configuration (mocapd.toml): reading, validation, and the command-line additions.

Why validate everything up front: the daemon runs unattended under systemd; a typo found
after the cameras are open, or at the first SIGHUP, is a robot without poses. Every problem
is one line naming the file, the key and what is wrong, raised as UserError before anything
opens. docs/daemon.md documents every key.

    rig = "rig.toml"                     # the calibrated rig (not needed with [sim])
    markerset = "set.toml"               # label markers live with this set (or "cmu41")
    runtime_dir = "/run/mocapd"          # control socket; default $RUNTIME_DIRECTORY etc.

    [pipeline]  mode = "triggered"|"greedy", fps, timeout_frames, pair_tolerance
    [tracker]   gate_px, max_missing, outlier_px, new_tracks_every, ...
    [rigid]     distance_tol_m, max_error_m
    [sim]       cameras, bodies, markers_per_body, extra_markers, fps, noise_px, dropout,
                ghosts, volume_m, size, seed, realtime, drop_camera, drop_from_s, drop_for_s,
                define_bodies, score, person, person_radius_m, unsync_ms, open_spread_s,
                clock_drift_ppm
    [sim.robot] port, start = [x, y, yaw_deg], delay_s, tau_s, max_speed_m_s,
                max_turn_rad_s, truth                      (a robot driven live, docs/simulator.md)
    [[rigid_body]] name, id, markers = [[x, y, z], ...], pivot, min_markers_start,
                   min_markers_keep, smoothing
    [[camera]]  name (a camera of the rig), source ("0" a device, a video, an image folder,
                "basler:SERIAL", "genicam:SERIAL"), fps (set on the camera; default: its
                own rate), threshold, min_area, max_area,
                timestamps ("device": the camera's own stamps where it gives them, or
                "arrival"), mask (a PNG, white where detection ignores pixels)
    [replay]    path (a .mcrec recording), realtime
    [[udp]]     address = "HOST:PORT", rate_hz, ttl, bodies, interface, markers
    [[serial]]  device, baud, rate_hz ("auto" or Hz), bodies
    [[mavlink]] device (a UART, or udpin:/udpout:/tcp:HOST:PORT), baud, body, message,
                frame, rate_hz ("auto" or Hz), system_id, component_id,
                origin = [lat_deg, lon_deg, alt_m]                          (docs/protocol.md)
    [natnet]    interface, command_port, data_port, multicast, group, up_axis, ttl, rate_hz,
                legacy_unlabeled, marker_sets, markerset_id, record_dir   (docs/natnet.md)
    [[vrpn]]    address = "HOST:PORT", rate_hz, udp                           (docs/vrpn.md)

The output tables are read in daemon.config.outputs, [zenoh] in daemon.config.zenoh.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field, fields, replace
from pathlib import Path

import numpy as np
import tomllib

from calibkit.core.errors import UserError
from daemon.config.check import (
    _bool,
    _check_keys,
    _list,
    _number,
    _string,
    _table,
    _Where,
    finite_number,
)
from daemon.config.outputs import (
    MavlinkOut,
    NatnetOut,
    SerialOut,
    UdpOut,
    VrpnOut,
    _mavlink,
    _natnet,
    _serial,
    _udp,
    _vrpn,
)
from daemon.config.zenoh import parse_daemon_zenoh
from daemon.tracking.rigid import BodyDef, RigidConfig
from daemon.tracking.tracker import TrackerConfig


@dataclass(frozen=True)
class SimRobot:
    """A simulated differential-drive robot driven live: (v, omega) commands come in as
    UDP datagrams on 127.0.0.1:port (daemon.synthetic.robot)."""

    port: int
    start: tuple[float, float, float] = (0.0, 0.0, 0.0)  # x, y (m), heading (degrees)
    delay_s: float = 0.05  # a command acts this long after it arrives
    tau_s: float = 0.1  # the speeds follow the delayed command with this time constant
    max_speed_m_s: float = 0.5  # commands are clipped to these
    max_turn_rad_s: float = 3.0
    truth: Path | None = None  # a CSV the robot's true path is written to (for scorers)


@dataclass(frozen=True)
class SimConfig:
    cameras: int = 8
    bodies: int = 3
    markers_per_body: int = 4
    extra_markers: int = 0  # loose markers besides the bodies'
    fps: float = 240.0
    noise_px: float = 0.2
    dropout: float = 0.0
    ghosts: float = 0.0
    volume_m: float = 4.0
    size: tuple[int, int] = (640, 480)
    seed: int = 0
    realtime: bool = True  # pace frames at fps; False: as fast as the tracker goes
    drop_camera: str = ""  # a camera that disconnects (fault injection)
    drop_from_s: float = 0.5
    drop_for_s: float = 0.5
    define_bodies: bool = True  # none configured: define the scene's bodies live at the start
    score: bool = True  # score each frame against the truth (off: the daemon's own cost alone)
    person: bool = False  # a person wearing the 41-marker set walks a circle (sim_person)
    person_radius_m: float = 1.0  # radius of that circle, about the volume's centre
    unsync_ms: float = 0.0  # cameras' clocks offset by up to this: unsynchronised cameras
    open_spread_s: float = 0.3  # cameras open up to this long after the first one
    clock_drift_ppm: float = 30.0  # each camera's clock gains or loses up to this
    robot: SimRobot | None = None  # a robot driven live ([sim.robot])


@dataclass(frozen=True)
class CameraIn:
    name: str
    source: str
    fps: float | None = None  # set on the camera (an image folder's timeline); None: its own
    threshold: float | str = "auto"
    min_area: float = 2.0
    max_area: float = 4000.0
    timestamps: str = "device"  # "arrival": ignore the camera's own timestamps and counter
    mask: Path | None = None  # PNG of pixels detection ignores (white), as `calibkit mask` writes


@dataclass(frozen=True)
class ReplayIn:
    path: Path
    realtime: bool = True


@dataclass(frozen=True)
class Config:
    path: Path | None = None
    rig: Path | None = None
    runtime_dir: Path | None = None
    mode: str = "triggered"
    fps: float = 240.0  # expected camera rate (the triggered multiplexer's timeout)
    timeout_frames: float = 1.5  # triggered: wait this many frame periods for a full set
    pair_tolerance: float = 0.5  # a set gathers samples within this many frame periods
    # live runs: SCHED_RR priority of the daemon's threads (0: normal scheduling)
    realtime_priority: int = 0  # SCHED_RR priority; 0: normal (`--realtime` turns it on)
    tracker: TrackerConfig = field(default_factory=TrackerConfig)
    # the [tracker] keys the file sets: the pixel gates it leaves out follow the rig's
    # residual (calibkit.vision.gates), the ones it sets stay as set
    tracker_keys: frozenset[str] = frozenset()
    rigid: RigidConfig = field(default_factory=RigidConfig)
    sim: SimConfig | None = None
    bodies: tuple[BodyDef, ...] = ()
    udp: tuple[UdpOut, ...] = ()
    serial: tuple[SerialOut, ...] = ()
    mavlink: tuple[MavlinkOut, ...] = ()
    cameras: tuple[CameraIn, ...] = ()
    replay: ReplayIn | None = None
    natnet: NatnetOut | None = None
    vrpn: tuple[VrpnOut, ...] = ()
    markerset: Path | None = None  # the marker set markers are labelled with live
    # a recording stops (keeping what it wrote) before its disk has less than this free
    record_min_free_mb: float = 100.0
    zenoh: object | None = None  # [zenoh]: capture nodes and poses (daemon.nodes.settings)


def _vectors(w, table, key, prefix, rows=None):
    v = table.get(key)
    try:
        a = np.asarray(v, dtype=np.float64)
    except (TypeError, ValueError):
        a = None
    want = "[x, y, z]" if rows == 1 else "a list of [x, y, z] in metres"
    if a is None or (rows == 1 and a.shape != (3,)) or (rows != 1 and (a.ndim != 2 or
                                                                       a.shape[1] != 3)):
        w.fail(prefix + key, f"expected {want}, got {v!r}")
    if not np.all(np.isfinite(a)):
        w.fail(prefix + key, "must be finite numbers")
    return a


def _dataclass_table(w, table, cls, default, prefix):
    """Overrides of a frozen config dataclass's numeric/bool fields from a TOML table."""
    names = {f.name: f for f in fields(cls) if f.name != "correspondence"}
    _check_keys(w, table, names, prefix)
    changes = {}
    for name in names:
        if name not in table:
            continue
        current = getattr(default, name)
        if isinstance(current, bool):
            changes[name] = _bool(w, table, name, prefix, current)
        elif isinstance(current, int):
            changes[name] = _number(w, table, name, prefix, current, int, lo=0)
        elif isinstance(current, float):
            changes[name] = _number(w, table, name, prefix, current, float, lo=0)
        elif isinstance(current, str):
            changes[name] = _string(w, table, name, prefix, current)
        elif isinstance(current, tuple):
            v = table[name]
            if not (isinstance(v, list) and len(v) == 2 and all(isinstance(x, int) for x in v)):
                w.fail(prefix + name, f"expected [width, height], got {v!r}")
            changes[name] = tuple(v)
    return replace(default, **changes)


def parse_config(data: dict, path: Path | None = None, base: Path | None = None) -> Config:
    """A Config from parsed TOML; relative paths are taken from `base` (the file's folder)."""
    w = _Where(path)
    top = {"rig", "runtime_dir", "markerset", "pipeline", "tracker", "rigid", "sim",
           "rigid_body", "udp", "serial", "mavlink", "natnet", "vrpn", "camera", "replay",
           "zenoh", "record_min_free_mb"}
    _check_keys(w, data, top, "")
    base = base or Path.cwd()
    cfg = Config(path=path)
    changes: dict = {}
    if "rig" in data:
        changes["rig"] = base / _string(w, data, "rig", "")
    if "runtime_dir" in data:
        changes["runtime_dir"] = base / _string(w, data, "runtime_dir", "")
    if "markerset" in data:
        changes["markerset"] = _markerset(w, _string(w, data, "markerset", ""), base)
    changes["record_min_free_mb"] = _number(w, data, "record_min_free_mb", "",
                                            cfg.record_min_free_mb, lo=0)
    pipe = _table(w, data, "pipeline")
    _check_keys(w, pipe, {"mode", "fps", "timeout_frames", "pair_tolerance",
                          "realtime_priority"}, "pipeline.")
    changes["mode"] = _string(w, pipe, "mode", "pipeline.", "triggered", ("triggered", "greedy"))
    changes["fps"] = _number(w, pipe, "fps", "pipeline.", cfg.fps, lo=1, hi=10000)
    changes["timeout_frames"] = _number(w, pipe, "timeout_frames", "pipeline.", 1.5, lo=0.1,
                                        hi=100)
    changes["pair_tolerance"] = _number(w, pipe, "pair_tolerance", "pipeline.", 0.5, lo=0.05,
                                        hi=0.5)
    changes["realtime_priority"] = _number(w, pipe, "realtime_priority", "pipeline.", 0,
                                           kind=int, lo=0, hi=99)
    changes["tracker"] = _dataclass_table(w, _table(w, data, "tracker"), TrackerConfig,
                                          TrackerConfig(), "tracker.")
    changes["tracker_keys"] = frozenset(_table(w, data, "tracker"))
    changes["rigid"] = _dataclass_table(w, _table(w, data, "rigid"), RigidConfig,
                                        RigidConfig(), "rigid.")
    if "sim" in data:
        table = dict(_table(w, data, "sim"))
        robot = table.pop("robot", None)
        sim = _dataclass_table(w, table, SimConfig, SimConfig(), "sim.")
        _sim_limits(w, sim)
        if robot is not None:
            sim = replace(sim, robot=_sim_robot(w, robot, base, sim.volume_m))
        changes["sim"] = sim
    changes["bodies"] = tuple(_bodies(w, data))
    changes["udp"] = tuple(_udp(w, t, f"udp[{i}].") for i, t in enumerate(_list(w, data, "udp")))
    changes["serial"] = tuple(_serial(w, t, f"serial[{i}].")
                              for i, t in enumerate(_list(w, data, "serial")))
    changes["mavlink"] = tuple(_mavlink(w, t, f"mavlink[{i}].")
                               for i, t in enumerate(_list(w, data, "mavlink")))
    changes["cameras"] = tuple(_camera(w, t, f"camera[{i}].", base)
                               for i, t in enumerate(_list(w, data, "camera")))
    if len({c.name for c in changes["cameras"]}) < len(changes["cameras"]):
        w.fail("camera", "two [[camera]] tables have the same name")
    if "replay" in data:
        t = _table(w, data, "replay")
        _check_keys(w, t, {"path", "realtime"}, "replay.")
        changes["replay"] = ReplayIn(base / _string(w, t, "path", "replay."),
                                     _bool(w, t, "realtime", "replay.", True))
    if "natnet" in data:
        changes["natnet"] = _natnet(w, _table(w, data, "natnet"), "natnet.", base)
        taken = {b.id for b in changes["bodies"]}
        if "markerset" in changes and changes["natnet"].markerset_id in taken:
            w.fail("natnet.markerset_id", f"{changes['natnet'].markerset_id} is a rigid "
                                          "body's id; the marker set needs an id of its own")
    changes["vrpn"] = tuple(_vrpn(w, t, f"vrpn[{i}].")
                            for i, t in enumerate(_list(w, data, "vrpn")))
    if "zenoh" in data or any(c.source.startswith("zenoh:") for c in changes["cameras"]):
        changes["zenoh"] = parse_daemon_zenoh(w, _table(w, data, "zenoh"), base)
    return replace(cfg, **changes)


def _markerset(w, value: str, base: Path) -> Path:
    """The marker set's file (a shipped set's name or a path), loaded once to check it."""
    # deferred on purpose: loads SciPy's optimisers, SciPy's sparse graphs... only where used
    from daemon.labelling.live import load, resolve, shipped_sets

    path = resolve(value, base)
    if not path.exists():
        w.fail("markerset", f"no marker set {value!r} (no file {path}; shipped sets: "
                            f"{', '.join(shipped_sets())})")
    try:
        load(path)
    except UserError as exc:
        w.fail("markerset", str(exc))
    return path


def _sim_limits(w, sim: SimConfig) -> None:
    if not 2 <= sim.cameras <= 32:
        w.fail("sim.cameras", f"must be between 2 and 32, got {sim.cameras}")
    if not 0 <= sim.bodies <= 20:
        w.fail("sim.bodies", f"must be between 0 and 20, got {sim.bodies}")
    if not 3 <= sim.markers_per_body <= 8:
        w.fail("sim.markers_per_body", f"must be between 3 and 8, got {sim.markers_per_body}")
    if sim.fps <= 0:
        w.fail("sim.fps", f"must be positive, got {sim.fps}")
    if not 0 <= sim.dropout < 1:
        w.fail("sim.dropout", f"must be in [0, 1), got {sim.dropout}")
    if not 0 <= sim.unsync_ms < 1000 / sim.fps:
        w.fail("sim.unsync_ms", f"must be in [0, {1000 / sim.fps:g}) (a frame period), "
                                f"got {sim.unsync_ms}")
    if not 0 <= sim.open_spread_s <= 30:
        w.fail("sim.open_spread_s", f"must be between 0 and 30, got {sim.open_spread_s}")
    if not 0 <= sim.clock_drift_ppm <= 1000:
        w.fail("sim.clock_drift_ppm", f"must be between 0 and 1000, got {sim.clock_drift_ppm}")
    if sim.person and not 0.3 <= sim.person_radius_m <= sim.volume_m / 2 - 0.3:
        w.fail("sim.person_radius_m", f"must be between 0.3 and {sim.volume_m / 2 - 0.3:g} "
                                      f"(inside the volume), got {sim.person_radius_m}")


def _sim_robot(w, t, base: Path, volume_m: float) -> SimRobot:
    p = "sim.robot."
    if not isinstance(t, dict):
        w.fail("sim.robot", f"expected a table [sim.robot], got {t!r}")
    _check_keys(w, t, {f.name for f in fields(SimRobot)}, p)
    if "port" not in t:
        w.fail(p + "port", "missing (required): the UDP port on 127.0.0.1 the robot's "
                           "commands come in on")
    start = t.get("start", [0.0, 0.0, 0.0])
    if not (isinstance(start, list) and len(start) == 3 and all(
            finite_number(v) for v in start)):
        w.fail(p + "start", f"expected [x, y, yaw_deg] (finite numbers), got {start!r}")
    if max(abs(start[0]), abs(start[1])) > 0.4 * volume_m:
        w.fail(p + "start", f"must be inside the volume's inner 80 % (|x|, |y| <= "
                            f"{0.4 * volume_m:g} m), got {start[:2]}")
    return SimRobot(
        port=_number(w, t, "port", p, 0, int, lo=1, hi=65535),
        start=tuple(float(v) for v in start),
        delay_s=_number(w, t, "delay_s", p, 0.05, lo=0.0, hi=2.0),
        tau_s=_number(w, t, "tau_s", p, 0.1, lo=0.001, hi=5.0),
        max_speed_m_s=_number(w, t, "max_speed_m_s", p, 0.5, lo=0.01, hi=10.0),
        max_turn_rad_s=_number(w, t, "max_turn_rad_s", p, 3.0, lo=0.01, hi=50.0),
        truth=base / _string(w, t, "truth", p) if "truth" in t else None)


def _bodies(w, data) -> list[BodyDef]:
    out, names, ids = [], set(), set()
    allowed = {"name", "id", "markers", "pivot", "min_markers_start", "min_markers_keep",
               "smoothing"}
    for i, t in enumerate(_list(w, data, "rigid_body")):
        p = f"rigid_body[{i}]."
        _check_keys(w, t, allowed, p)
        name = _string(w, t, "name", p)
        p = f"rigid_body[{i}] ({name})."
        if "id" not in t:
            w.fail(p + "id", "missing (required)")
        body_id = _number(w, t, "id", p, 0, int, lo=0, hi=65535)
        markers = _vectors(w, t, "markers", p)
        if not 3 <= len(markers) <= 32:
            w.fail(p + "markers", f"a rigid body needs 3 to 32 markers, got {len(markers)}")
        d = np.linalg.norm(markers[:, None] - markers[None], axis=2)
        d = d[np.triu_indices(len(markers), 1)]
        if d.min() < 0.01:
            w.fail(p + "markers", f"two markers are {d.min() * 1000:.1f} mm apart; markers "
                                  "need at least 10 mm between them")
        pivot = _vectors(w, t, "pivot", p, rows=1) if "pivot" in t else np.zeros(3)
        k = len(markers)
        start = _number(w, t, "min_markers_start", p, min(k, 4) if k >= 4 else 3, int, 3, k)
        keep = _number(w, t, "min_markers_keep", p, 3, int, 3, k)
        smoothing = _number(w, t, "smoothing", p, 0.0, float, 0.0, 0.99)
        if name in names:
            w.fail(p + "name", f"two rigid bodies are called {name!r}")
        if body_id in ids:
            w.fail(p + "id", f"two rigid bodies have id {body_id}")
        names.add(name)
        ids.add(body_id)
        out.append(BodyDef(name, body_id, markers, pivot, start, keep, smoothing))
    return out


def _camera(w, t, p, base: Path) -> CameraIn:
    _check_keys(w, t, {"name", "source", "fps", "threshold", "min_area", "max_area",
                       "timestamps", "mask"}, p)
    threshold = t.get("threshold", "auto")
    if threshold != "auto" and (isinstance(threshold, bool)
                                or not isinstance(threshold, (int, float))
                                or not 0 < threshold < 65536):
        w.fail(p + "threshold", f'expected "auto" or a pixel value, got {threshold!r}')
    source = str(_string(w, t, "source", p))
    if not source.isdigit() and ":" not in source and (base / source).exists():
        source = str(base / source)  # files and folders are relative to the configuration
    mask = None
    if "mask" in t:
        mask = base / _string(w, t, "mask", p)
        if not mask.is_file():
            w.fail(p + "mask", f"{mask} not found; make one with `calibkit mask SOURCE --out "
                               f"{mask.name}` or from the live view")
    return CameraIn(_string(w, t, "name", p), source,
                    _number(w, t, "fps", p, None, lo=0.1, hi=10000), threshold,
                    _number(w, t, "min_area", p, 2.0, lo=0), _number(w, t, "max_area", p,
                                                                     4000.0, lo=1),
                    _string(w, t, "timestamps", p, "device", ("device", "arrival")), mask)


def load_config(path: str | Path | None) -> Config:
    """Read and validate a mocapd.toml; None gives the defaults (flags add the rest)."""
    if path is None:
        return Config()
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise UserError(f"{path}: no such configuration file") from None
    except OSError as exc:
        raise UserError(f"{path}: cannot read: {exc.strerror}") from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise UserError(f"{path}: not valid TOML: {exc}") from None
    return parse_config(data, path, path.parent)


def default_runtime_dir() -> Path:
    """Where the control socket lives: systemd's RuntimeDirectory, else the user's runtime
    directory, else /tmp."""
    if os.environ.get("MOCAPD_RUNTIME_DIR"):
        return Path(os.environ["MOCAPD_RUNTIME_DIR"])
    if os.environ.get("RUNTIME_DIRECTORY"):
        return Path(os.environ["RUNTIME_DIRECTORY"].split(":")[0])
    if os.environ.get("XDG_RUNTIME_DIR"):
        return Path(os.environ["XDG_RUNTIME_DIR"]) / "mocapd"
    return Path(f"/tmp/mocapd-{os.getuid()}")
