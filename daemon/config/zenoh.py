"""mocapd.toml's [zenoh] table (keys rig, listen, connect, multicast_scouting, cameras, poses,
timeout_ms, max_lag_ms): the daemon's Zenoh session, which cameras come from capture
nodes, and whether poses go out over Zenoh (the nodes' own files are daemon.nodes.settings).
Apart from those so that daemon.config.mocapd can read it without importing them back."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from daemon.config.check import _bool, _check_keys, _number, _string
from daemon.publish.zenoh_session import ZenohSettings, check_endpoint, check_name, read_users

DEFAULT_PORT = 7447  # Zenoh's own default port


@dataclass(frozen=True)
class DaemonZenoh:
    """mocapd.toml's [zenoh]: the daemon's session, which cameras come from nodes, and
    whether poses go out over Zenoh."""

    session: ZenohSettings = field(default_factory=ZenohSettings)
    cameras: str = "configured"  # "announced": every rig camera without a [[camera]] table
    poses: bool = True  # publish mocap/<rig>/bodies/<name>
    timeout_ms: float = 250.0  # a camera silent this long is dropped (its node died)
    max_lag_ms: float = 100.0  # a sample older than this on arrival is late (node behind)


def _session(w, t, prefix: str, listen_default=(), base: Path | None = None) -> ZenohSettings:
    def endpoints(key, default):
        v = t.get(key, list(default))
        if isinstance(v, str):
            v = [v]
        if not isinstance(v, list):
            w.fail(prefix + key, f"expected a list of endpoints, got {v!r}")
        try:
            return tuple(check_endpoint(e) for e in v)
        except ValueError as exc:
            w.fail(prefix + key, str(exc))

    rig = _string(w, t, "rig", prefix, "default")
    try:
        check_name(rig, "rig")
    except ValueError as exc:
        w.fail(prefix + "rig", str(exc))
    user = _string(w, t, "user", prefix, "")
    password = _string(w, t, "password", prefix, "")
    if bool(user) != bool(password) or ":" in user:
        w.fail(prefix + ("password" if user else "user"),
               "give user and password together (a user name has no ':')")
    users_file = ""
    if "users_file" in t:
        path = (base or Path.cwd()) / _string(w, t, "users_file", prefix)
        try:
            read_users(path)
        except OSError as exc:
            w.fail(prefix + "users_file", f"cannot read {path}: {exc.strerror}")
        except ValueError as exc:
            w.fail(prefix + "users_file", f"{path}: {exc}")
        users_file = str(path)
    return ZenohSettings(rig, endpoints("listen", listen_default), endpoints("connect", ()),
                         _bool(w, t, "multicast_scouting", prefix, False), user, password,
                         users_file)


def parse_daemon_zenoh(w, t: dict, base: Path | None = None) -> DaemonZenoh:
    """mocapd.toml's [zenoh] table (`w`: daemon.config.mocapd's error helper)."""
    p = "zenoh."
    _check_keys(w, t, {"rig", "listen", "connect", "multicast_scouting", "cameras", "poses",
                       "timeout_ms", "max_lag_ms", "user", "password", "users_file"}, p)
    session = _session(w, t, p, (f"tcp/0.0.0.0:{DEFAULT_PORT}",), base)
    return DaemonZenoh(session, _string(w, t, "cameras", p, "configured",
                                        ("configured", "announced")),
                       _bool(w, t, "poses", p, True),
                       _number(w, t, "timeout_ms", p, 250.0, lo=20, hi=60_000),
                       _number(w, t, "max_lag_ms", p, 100.0, lo=1, hi=60_000))


def is_remote(source: str) -> bool:
    """Whether a [[camera]] source names a camera served by a node ("zenoh:<camera>")."""
    return source.startswith("zenoh:")
