"""UDP output: the binary pose packet (packet.py) to unicast and multicast addresses."""

from __future__ import annotations

import ipaddress
import socket
import time

from daemon.publish.base import Publisher
from daemon.publish.packet import encode


def result_packet(result, body_ids=None, markers: bool = False) -> bytes:
    """The packet for a FrameResult, for all bodies or those whose ids are listed; with
    `markers`, the labelled markers too when the frame has them (a marker set is
    configured). Serial leaves them out: a 41-marker frame is 660 bytes more."""
    p = result.poses
    sel = slice(None) if body_ids is None else [i for i, b in enumerate(p.ids) if b in body_ids]
    lab = getattr(result, "labelled", None) if markers else None
    extra = None if lab is None else (len(lab.names), lab.index, lab.confidence, lab.xyz)
    return encode(result.frame, result.t_ns, time.monotonic_ns() - result.arrival_ns,
                  p.ids[sel], p.valid[sel], p.n_markers[sel], p.position[sel],
                  p.quaternion[sel], p.error_m[sel], extra)


class UdpPublisher(Publisher):
    """One socket sending each frame's packet to every target (HOST, PORT)."""

    inline = True  # a non-blocking sendto never waits: no thread hand-off on the way out

    def __init__(self, targets: list[tuple[str, int]], ttl: int = 1, rate_hz: float = 0.0,
                 bodies: list[int] | None = None, name: str = "udp",
                 interface: str | None = None, markers: bool = True) -> None:
        """`interface`: the local address multicast leaves from (default: the route's);
        `markers`: send the labelled markers when a marker set is configured."""
        super().__init__(rate_hz=rate_hz)
        self.targets = list(targets)
        self.ttl = ttl
        self.interface = interface
        self.bodies = bodies
        self.markers = markers
        self.name = name
        self.sock: socket.socket | None = None

    def open(self) -> None:
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sock.setblocking(False)
        if any(ipaddress.ip_address(socket.gethostbyname(h)).is_multicast
               for h, _ in self.targets):
            sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, self.ttl)
            if self.interface:
                sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF,
                                socket.inet_aton(self.interface))
        self.sock = sock

    def send(self, result) -> None:
        data = result_packet(result, self.bodies, self.markers)
        failures = []
        for target in self.targets:
            try:
                self.sock.sendto(data, target)
            except (BlockingIOError, ConnectionRefusedError):
                pass  # a full buffer or nobody listening: a datagram lost, as UDP allows
            except OSError as exc:  # unreachable network, no route: log it, keep going
                failures.append(f"{target[0]}:{target[1]}: {exc.strerror or exc}")
        if failures:
            self._failed("; ".join(failures))

    def close(self) -> None:
        if self.sock is not None:
            self.sock.close()
            self.sock = None
