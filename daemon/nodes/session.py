"""Zenoh sessions for mocapd's nodes and daemon, configured explicitly: no guessing.

Zenoh's defaults scout for peers by UDP multicast and listen on every interface. A lab
wants the opposite by default: the daemon listens on the endpoints it is given, each node
connects to the daemon's, and nothing multicasts unless asked (`multicast_scouting`).
Peers talk to the peers they connect to; gossip (peers telling each other about the
peers they know) stays off with multicast, so a node never tries to reach another node.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass

from calibkit.core.errors import UserError

ENDPOINT = re.compile(r"^(tcp|udp|quic|tls|unixsock-stream)/.+$")
KEY_CHUNK = re.compile(r"^[A-Za-z0-9_.\-]+$")  # a camera, body, node or rig name in a key


@dataclass(frozen=True)
class ZenohSettings:
    """How a process joins the Zenoh network: where it listens and what it connects to."""

    rig: str = "default"  # the key prefix: mocap/<rig>/...
    listen: tuple[str, ...] = ()
    connect: tuple[str, ...] = ()
    multicast_scouting: bool = False

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
        return conf

    def open(self):
        """An open zenoh.Session; a bad endpoint or a busy port is the user's to fix."""
        # deferred on purpose: loads Zenoh only where used
        import zenoh

        try:
            return zenoh.open(self.config())
        except Exception as exc:  # noqa: BLE001 - zenoh raises its own ZError
            where = ", ".join(self.listen) or ", ".join(self.connect) or "no endpoint"
            raise UserError(f"zenoh: cannot open a session ({where}): {exc}") from None


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
