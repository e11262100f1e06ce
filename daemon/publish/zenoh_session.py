"""Zenoh sessions for mocapd's nodes and daemon, configured explicitly: no guessing.

Zenoh's defaults scout for peers by UDP multicast and listen on every interface. A lab
wants the opposite by default: the daemon listens on the endpoints it is given, each node
connects to the daemon's, and nothing multicasts unless asked (`multicast_scouting`).
Peers talk to the peers they connect to; gossip (peers telling each other about the
peers they know) stays off with multicast, so a node never tries to reach another node.

Who may join: with `users_file` (lines `user:password`), Zenoh's own user-password
authentication admits only peers that present one of its users (`user`, `password` in the
joining side's file); others are refused at the handshake, before any message. A session
that listens beyond loopback with no users file says once that anyone who reaches the port
may send it blobs.
"""

from __future__ import annotations

import ipaddress
import json
import logging
import re
from dataclasses import dataclass
from pathlib import Path

from calibkit.core.errors import UserError

ENDPOINT = re.compile(r"^(tcp|udp|quic|tls|unixsock-stream)/.+$")
KEY_CHUNK = re.compile(r"^[A-Za-z0-9_.\-]+$")  # a camera, body, node or rig name in a key
log = logging.getLogger("mocapd.zenoh")


@dataclass(frozen=True)
class ZenohSettings:
    """How a process joins the Zenoh network: where it listens and what it connects to."""

    rig: str = "default"  # the key prefix: mocap/<rig>/...
    listen: tuple[str, ...] = ()
    connect: tuple[str, ...] = ()
    multicast_scouting: bool = False
    user: str = ""  # the credentials this side presents to a peer that asks for them
    password: str = ""
    users_file: str = ""  # who may join this side: lines user:password ("" : anyone)

    def exposed(self) -> list[str]:
        """Listen endpoints beyond loopback that any host reaching them may join."""
        if self.users_file:
            return []
        return [e for e in self.listen if not _loopback(e)]

    def config(self):
        """A zenoh.Config for a peer with exactly these endpoints."""
        # deferred on purpose: loads Zenoh only where used
        import zenoh

        conf = zenoh.Config()
        conf.insert_json5("mode", json.dumps("peer"))
        conf.insert_json5("listen/endpoints", json.dumps(list(self.listen)))
        conf.insert_json5("connect/endpoints", json.dumps(list(self.connect)))
        conf.insert_json5("scouting/multicast/enabled",
                          json.dumps(bool(self.multicast_scouting)))
        conf.insert_json5("scouting/gossip/enabled", json.dumps(bool(self.multicast_scouting)))
        # keep retrying the daemon's endpoint: nodes may start before it
        conf.insert_json5("connect/timeout_ms", "-1")
        conf.insert_json5("connect/exit_on_failure", "false")
        auth = {}
        if self.user:
            auth.update(user=self.user, password=self.password)
        if self.users_file:
            auth["dictionary_file"] = str(Path(self.users_file).resolve())
        if auth:
            conf.insert_json5("transport/auth/usrpwd", json.dumps(auth))
        return conf

    def open(self):
        """An open zenoh.Session; a bad endpoint or a busy port is the user's to fix."""
        # deferred on purpose: loads Zenoh only where used
        import zenoh

        for endpoint in self.exposed():
            log.warning("zenoh: listening on %s with no access control: any host that reaches "
                        "it may join and send blobs; set users_file in [zenoh] (docs/nodes.md)",
                        endpoint)
        try:
            return zenoh.open(self.config())
        except Exception as exc:  # noqa: BLE001 - zenoh raises its own ZError
            where = ", ".join(self.listen) or ", ".join(self.connect) or "no endpoint"
            raise UserError(f"zenoh: cannot open a session ({where}): {exc}") from None


def _loopback(endpoint: str) -> bool:
    """Whether a locator's address is this computer's own (127.0.0.0/8, ::1, localhost)."""
    if endpoint.startswith("unixsock-stream/"):
        return True
    host = endpoint.split("/", 1)[1].rsplit(":", 1)[0].strip("[]")
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def read_users(path: Path) -> list[str]:
    """The user names of a users file (lines `user:password`, read by Zenoh as they are: no
    comments, spaces belong to the name or password); ValueError with the line at fault, so
    a typo is found at start, not as nodes refused for no visible reason."""
    names = []
    for n, line in enumerate(Path(path).read_text(encoding="utf-8").splitlines(), 1):
        if not line.strip():
            continue
        user, sep, password = line.partition(":")
        if not sep or not user or not password or user != user.strip():
            raise ValueError(f"line {n}: expected user:password (Zenoh reads the file as "
                             "it is: no comments, no spaces around the name)")
        names.append(user)
    if not names:
        raise ValueError("no user:password line")
    return names


def check_endpoint(text: str) -> str:
    """A Zenoh locator such as tcp/127.0.0.1:7447; ValueError with the reason."""
    if not isinstance(text, str) or not ENDPOINT.match(text):
        raise ValueError(f"expected a Zenoh endpoint such as tcp/192.168.1.10:7447, got {text!r}")
    return text


def check_name(text: str, what: str) -> str:
    """A name that goes into a key (letters, digits, _ . -); ValueError with the reason."""
    if not isinstance(text, str) or not KEY_CHUNK.match(text):
        raise ValueError(f"{what} {text!r} cannot go into a Zenoh key: use letters, digits, "
                         "'_', '.' or '-'")
    return text


# ---- keys ----------------------------------------------------------------------------------

def blobs_key(rig: str, camera: str) -> str:
    return f"mocap/{rig}/{camera}/blobs"


def sets_key(rig: str, node: str) -> str:
    return f"mocap/{rig}/_nodes/{node}/blobs"


def all_sets_key(rig: str) -> str:
    return f"mocap/{rig}/_nodes/*/blobs"


def all_blobs_key(rig: str) -> str:
    return f"mocap/{rig}/*/blobs"


def ping_key(rig: str) -> str:
    return f"mocap/{rig}/_clock/ping"


def pong_key(rig: str, node: str) -> str:
    return f"mocap/{rig}/_nodes/{node}/clock"


def announce_key(rig: str, node: str) -> str:
    return f"mocap/{rig}/_nodes/{node}/announce"


def body_key(rig: str, body: str) -> str:
    return f"mocap/{rig}/bodies/{body}"
