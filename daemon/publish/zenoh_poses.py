"""Zenoh output: each rigid body's pose on mocap/<rig>/bodies/<name> (docs/protocol.md).

Consumers on other machines subscribe with any Zenoh client (Python, C, Rust, ROS 2
through rmw_zenoh or zenoh-bridge-ros2dds) without NatNet or VRPN. One message per body
per frame, the fixed 60-byte pose record of daemon.publish.zenoh_wire; a body not seen this
frame is sent with its valid flag clear, so a consumer can tell "lost" from "no data".
The session is the daemon's (the nodes' hub): the poses leave by the endpoints the nodes
reach it on. Puts are express and dropped under congestion, so a slow subscriber never
holds up the frame loop (and the base class keeps it off the frame loop anyway).
"""

from __future__ import annotations

import time

from daemon.publish import zenoh_wire as wire
from daemon.publish.base import Publisher
from daemon.publish.zenoh_session import body_key


class ZenohPosePublisher(Publisher):
    """Every configured body's pose, one Zenoh publisher per body."""

    def __init__(self, hub, bodies=(), rate_hz: float = 0.0) -> None:
        super().__init__(rate_hz=rate_hz)
        self.hub = hub
        self.names = {int(b.id): b.name for b in bodies}
        self.name = f"zenoh:mocap/{hub.rig}/bodies"
        self._pubs: dict[int, object] = {}

    def open(self) -> None:
        if self.hub.session is None:
            raise OSError("the Zenoh session is not open yet")
        self._pubs = {}

    def _publisher(self, body_id: int):
        pub = self._pubs.get(body_id)
        if pub is None:
            # deferred on purpose: loads Zenoh only where used
            import zenoh

            name = self.names.get(body_id, f"body{body_id}")
            pub = self._pubs[body_id] = self.hub.session.declare_publisher(
                body_key(self.hub.rig, name), express=True,
                congestion_control=zenoh.CongestionControl.DROP)
        return pub

    def send(self, result) -> None:
        p = result.poses
        latency = time.monotonic_ns() - result.arrival_ns
        for k, body_id in enumerate(p.ids.tolist()):
            valid = bool(p.valid[k])
            self._publisher(body_id).put(wire.encode_pose(
                body_id, result.frame, result.t_ns, latency, valid, int(p.n_markers[k]),
                p.position[k] if valid else (0.0, 0.0, 0.0),
                p.quaternion[k] if valid else (0.0, 0.0, 0.0, 1.0),
                p.error_m[k] if valid else 0.0))

    def close(self) -> None:
        for pub in self._pubs.values():
            try:
                pub.undeclare()
            except Exception:  # noqa: BLE001 - the session may already be closed
                pass
        self._pubs = {}
