"""A capture node's node.toml (mocapd.toml's [zenoh] table is daemon.config.zenoh).

Checked up front as mocapd.toml is (daemon.config.mocapd): one line naming the file, the key and
the problem, before anything opens.

    node.toml     name, realtime_priority, publish, set_wait_ms,
                  [zenoh] (rig, listen, connect, multicast_scouting),
                  [[camera]] (as mocapd.toml's), [sim] (as mocapd.toml's),
                  [node_sim] cameras, clock_offset_ms, clock_drift_ppm
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

import tomllib

from calibkit.core.errors import UserError
from daemon.config.check import _check_keys, _list, _number, _string, _table, _Where
from daemon.config.mocapd import CameraIn, SimConfig, _camera, _dataclass_table, _sim_limits
from daemon.config.zenoh import DEFAULT_PORT, _session
from daemon.publish.zenoh_session import ZenohSettings, check_name

PUBLISH = ("cameras", "sets")


@dataclass(frozen=True)
class NodeConfig:
    """A capture node: its name, its session, and the cameras it serves."""

    name: str = "node"
    path: Path | None = None
    session: ZenohSettings = field(default_factory=lambda: ZenohSettings(
        connect=(f"tcp/127.0.0.1:{DEFAULT_PORT}",)))
    cameras: tuple[CameraIn, ...] = ()
    sim: SimConfig | None = None
    sim_cameras: tuple[str, ...] = ()  # which of the simulated rig's cameras it serves
    clock_offset_ms: float = 0.0  # --sim: the node's own clock against the machine's
    clock_drift_ppm: float = 0.0
    # SCHED_RR of the capture threads, its network one step above (0: normal; --realtime: 9)
    realtime_priority: int = 0
    # "cameras": one message per camera frame, on the camera's own key; "sets": one message
    # per trigger with every camera's frame (daemon.nodes.node.SetPublisher)
    publish: str = "sets"
    set_wait_ms: float = 2.0  # how long a set waits for a camera whose frame has not come


def parse_node_config(data: dict, path: Path | None = None,
                      base: Path | None = None) -> NodeConfig:
    w = _Where(path)
    _check_keys(w, data, {"name", "realtime_priority", "publish", "set_wait_ms", "zenoh",
                          "camera", "sim", "node_sim"}, "")
    name = _string(w, data, "name", "", "node")
    priority = _number(w, data, "realtime_priority", "", 0, kind=int, lo=0, hi=99)
    publish = _string(w, data, "publish", "", "sets", choices=PUBLISH)
    set_wait = _number(w, data, "set_wait_ms", "", 2.0, lo=0.0, hi=1000.0)
    try:
        check_name(name, "node name")
    except ValueError as exc:
        w.fail("name", str(exc))
    zt = _table(w, data, "zenoh")
    _check_keys(w, zt, {"rig", "listen", "connect", "multicast_scouting", "user", "password",
                        "users_file"}, "zenoh.")
    session = _session(w, zt, "zenoh.", (), base)
    if not session.connect and not session.listen:
        session = replace(session, connect=(f"tcp/127.0.0.1:{DEFAULT_PORT}",))
    cameras = tuple(_camera(w, t, f"camera[{i}].", base or Path.cwd())
                    for i, t in enumerate(_list(w, data, "camera")))
    for i, c in enumerate(cameras):
        try:
            check_name(c.name, "camera name")
        except ValueError as exc:
            w.fail(f"camera[{i}].name", str(exc))
    sim = None
    if "sim" in data:
        sim = _dataclass_table(w, _table(w, data, "sim"), SimConfig, SimConfig(), "sim.")
        _sim_limits(w, sim)
    ns = _table(w, data, "node_sim")
    _check_keys(w, ns, {"cameras", "clock_offset_ms", "clock_drift_ppm"}, "node_sim.")
    serve = ns.get("cameras", [])
    if not isinstance(serve, list) or not all(isinstance(c, str) for c in serve):
        w.fail("node_sim.cameras", f"expected a list of camera names, got {serve!r}")
    return NodeConfig(name, path, session, cameras, sim, tuple(serve),
                      _number(w, ns, "clock_offset_ms", "node_sim.", 0.0, lo=-1e9, hi=1e9),
                      _number(w, ns, "clock_drift_ppm", "node_sim.", 0.0, lo=-1000,
                              hi=1000), priority, publish, set_wait)


def load_node_config(path: str | Path | None) -> NodeConfig:
    if path is None:
        return NodeConfig()
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise UserError(f"{path}: no such node configuration file") from None
    except OSError as exc:
        raise UserError(f"{path}: cannot read: {exc.strerror}") from None
    except tomllib.TOMLDecodeError as exc:
        raise UserError(f"{path}: not valid TOML: {exc}") from None
    return parse_node_config(data, path, path.parent)


def parse_camera_list(text: str, names: list[str]) -> tuple[str, ...]:
    """"cam0,cam3" or "0-7" or "0,2,5" -> camera names of the rig; ValueError otherwise."""
    out: list[str] = []
    for part in (p.strip() for p in text.split(",") if p.strip()):
        lo, dash, hi = part.partition("-")
        if part in names:
            out.append(part)
        elif lo.isdigit() and (not dash or hi.isdigit()):
            a, b = int(lo), int(hi) if dash else int(lo)
            if not 0 <= a <= b < len(names):
                raise ValueError(f"cameras {part!r}: the rig has cameras 0-{len(names) - 1}")
            out.extend(names[a:b + 1])
        else:
            raise ValueError(f"no camera {part!r} in the rig ({', '.join(names)})")
    if len(set(out)) < len(out):
        raise ValueError(f"a camera is listed twice in {text!r}")
    return tuple(out)
