"""Reading mocapd's serial pose stream in a program: frames off a UART, the newest pose.

    from mocap_serial import SerialPoseReader
    rx = SerialPoseReader("/dev/ttyUSB0", 115200)   # mocapd's [[serial]] line, far end
    pose = rx.latest(body_id=1, timeout_s=1.0)       # a Pose: t_ns, position, yaw, ...

On the line each packet is followed by its CRC-16, COBS-encoded and ended by a zero byte
(docs/protocol.md); daemon/publish/packet.py decodes it. A controller wants the newest pose,
not a queue of old ones: `latest` reads everything waiting and keeps the last valid pose of
the body. `t_ns` is when the cameras took the frame, on the daemon's monotonic clock (the
same clock as `time.monotonic_ns()` on the daemon's machine).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from daemon.publish.packet import decode, read_serial_frame


@dataclass(frozen=True)
class Pose:
    frame: int
    t_ns: int  # capture time, the daemon's monotonic clock
    position: np.ndarray  # (3,) metres
    quaternion: np.ndarray  # (4,) x y z w, body to world
    received_ns: int  # when this program read it (its monotonic clock)

    @property
    def yaw(self) -> float:
        """Heading about z (radians): the body's x axis in the floor plane."""
        x, y, z, w = (float(v) for v in self.quaternion)
        return math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))


def frames_in(buffer: bytearray) -> list[bytes]:
    """The whole frames (without delimiters) at the front of buffer, removed from it."""
    out = []
    while True:
        end = buffer.find(b"\x00")
        if end < 0:
            return out
        out.append(bytes(buffer[:end]))
        del buffer[:end + 1]


def packets(frames: list[bytes]) -> list:
    """Decoded packets of serial frames; a frame that fails its CRC (a line glitch, or the
    partial frame a reader starts in the middle of) is skipped."""
    out = []
    for f in frames:
        try:
            out.append(decode(read_serial_frame(f)))
        except ValueError:
            continue
    return out


def body_pose(packet, body_id: int, received_ns: int) -> Pose | None:
    hit = np.flatnonzero((packet.ids == body_id) & packet.valid)
    if not len(hit):
        return None
    b = hit[0]
    return Pose(packet.frame, packet.t_ns, packet.position[b].astype(float),
                packet.quaternion[b].astype(float), received_ns)


class SerialPoseReader:
    """The far end of a mocapd serial output (a UART, or a pseudo-terminal on the
    simulator)."""

    def __init__(self, device: str, baud: int = 115200) -> None:
        import serial

        self.port = serial.Serial(device, baud, timeout=0.05)
        self.buffer = bytearray()
        self.skipped = 0

    def read_packets(self, timeout_s: float = 0.05) -> list:
        """Every packet that has come in (waits up to timeout_s for the first)."""
        self.port.timeout = timeout_s
        data = self.port.read(max(1, self.port.in_waiting))
        if self.port.in_waiting:
            data += self.port.read(self.port.in_waiting)
        self.buffer += data
        frames = frames_in(self.buffer)
        got = packets(frames)
        self.skipped += len(frames) - len(got)
        return got

    def latest(self, body_id: int, timeout_s: float = 1.0) -> Pose:
        """The newest valid pose of the body among what has come in, waiting for one if
        none has; TimeoutError after timeout_s without one."""
        deadline = time.monotonic() + timeout_s
        while True:
            got = [p for p in (body_pose(k, body_id, time.monotonic_ns())
                               for k in self.read_packets()) if p is not None]
            if got:
                return got[-1]
            if time.monotonic() > deadline:
                raise TimeoutError(f"no valid pose of body {body_id} within {timeout_s} s")

    def close(self) -> None:
        self.port.close()
