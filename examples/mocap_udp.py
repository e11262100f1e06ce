"""Reading mocapd's UDP pose stream in a program: the latest pose of one body.

    from mocap_udp import PoseReceiver
    rx = PoseReceiver(9870)             # the port of mocapd.toml's [[udp]] address
    position, rotation = rx.latest(body_id=1, timeout_s=1.0)

Each datagram is one frame (daemon/publish/packet.py decodes it, docs/protocol.md describes
it). A program that draws or steers wants the newest pose, not a queue of old ones, so
`latest` reads everything waiting and keeps the last valid pose of the body asked for.
"""

from __future__ import annotations

import socket
import time

import numpy as np
from scipy.spatial.transform import Rotation

from daemon.publish.packet import decode


class PoseReceiver:
    """A UDP socket bound to mocapd's output port."""

    def __init__(self, port: int, host: str = "127.0.0.1") -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind((host, port))
        self.frame = -1

    def latest(self, body_id: int, timeout_s: float = 1.0):
        """(position (3,), rotation 3x3 body to world) of the newest valid pose of the body;
        TimeoutError when none comes within timeout_s."""
        deadline = time.monotonic() + timeout_s
        found = None
        self.sock.settimeout(timeout_s)
        while True:
            try:
                data = self.sock.recv(65536)
            except (TimeoutError, BlockingIOError):
                if found is not None:
                    return found
                raise TimeoutError(f"no valid pose of body {body_id} within {timeout_s} s")\
                    from None
            packet = decode(data)
            hit = np.flatnonzero((packet.ids == body_id) & packet.valid)
            if len(hit):
                b = hit[0]
                self.frame = packet.frame
                found = (packet.position[b].astype(float),
                         Rotation.from_quat(packet.quaternion[b].astype(float)).as_matrix())
            if found is not None:
                self.sock.setblocking(False)  # drain what is waiting, keep the newest
            elif time.monotonic() > deadline:
                raise TimeoutError(f"no valid pose of body {body_id} within {timeout_s} s")

    def every(self, body_id: int, timeout_s: float = 1.0):
        """Every frame's (frame, t_ns, valid, position (3,), rotation 3x3) of the body, in
        order, for programs that want the whole path (painting, logging); stops after
        timeout_s with no packet."""
        self.sock.settimeout(timeout_s)
        while True:
            try:
                data = self.sock.recv(65536)
            except TimeoutError:
                return
            packet = decode(data)
            hit = np.flatnonzero(packet.ids == body_id)
            if not len(hit):
                continue
            b = hit[0]
            self.frame = packet.frame
            valid = bool(packet.valid[b])
            rotation = Rotation.from_quat(packet.quaternion[b].astype(float)).as_matrix() \
                if valid else None
            yield packet.frame, packet.t_ns, valid, packet.position[b].astype(float), rotation

    def close(self) -> None:
        self.sock.close()
