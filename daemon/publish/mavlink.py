"""MAVLink output for flight controllers: one body's pose in NED, as the autopilot expects.

Messages: VISION_POSITION_ESTIMATE (PX4 and ArduPilot), ODOMETRY (PX4's EKF2) or
ATT_POS_MOCAP (ArduPilot). Our world is z up; `frame` says how its axes lie: "enu"
(x east, y north) or "flu" (x forward/north, y left/west). Positions go to NED and the
body's axes from FLU to FRD. Covariance is unknown: its first element is NaN, as the
MAVLink spec says. An invalid body sends nothing (an autopilot must not fuse a stale pose).

The link (daemon.publish.mavlink_link) lives on its own thread from start: HEARTBEAT,
TIMESYNC answers and the origin go out whether or not a pose does, and a link that fails
(a UART unplugged, a TCP peer gone) is reopened there once a second.
"""

from __future__ import annotations

import logging
import math
import threading
import time

import numpy as np

from daemon.process.supervise import Supervised
from daemon.publish.base import Publisher
from daemon.publish.mavlink_link import MavlinkLink

log = logging.getLogger("mocapd.publish")

MESSAGES = ("vision_position_estimate", "odometry", "att_pos_mocap")
WORLD_TO_NED = {
    "enu": np.array([[0.0, 1, 0], [1, 0, 0], [0, 0, -1]]),
    "flu": np.diag([1.0, -1, -1]),
}
FLU_TO_FRD = np.diag([1.0, -1, -1])
MAV_FRAME_LOCAL_FRD = 20
MAV_FRAME_BODY_FRD = 12
MAV_ESTIMATOR_TYPE_MOCAP = 6


def to_ned(position: np.ndarray, rotation: np.ndarray, frame: str = "enu"):
    """World position (3,) and body-to-world rotation (3, 3) -> NED position and the
    FRD-body-to-NED rotation."""
    A = WORLD_TO_NED[frame]
    return A @ position, A @ rotation @ FLU_TO_FRD


def euler_zyx(R: np.ndarray) -> tuple[float, float, float]:
    """(roll, pitch, yaw) radians of a rotation, aerospace ZYX order."""
    pitch = -math.asin(max(-1.0, min(1.0, R[2, 0])))
    roll = math.atan2(R[2, 1], R[2, 2])
    yaw = math.atan2(R[1, 0], R[0, 0])
    return roll, pitch, yaw


def quaternion_wxyz(R: np.ndarray) -> list[float]:
    # deferred on purpose: loads numba (compiled kernels) only where used
    from daemon.tracking.rigid import quaternion_xyzw

    x, y, z, w = quaternion_xyzw(R[None])[0]
    return [float(w), float(x), float(y), float(z)]


def mavlink_message(mav, message: str, t_us: int, position, rotation, frame: str = "enu"):
    """The pymavlink message object for one pose."""
    p, R = to_ned(np.asarray(position, dtype=np.float64), np.asarray(rotation), frame)
    x, y, z = (float(v) for v in p)
    cov = [math.nan] + [0.0] * 20
    if message == "vision_position_estimate":
        roll, pitch, yaw = euler_zyx(R)
        return mav.vision_position_estimate_encode(t_us, x, y, z, roll, pitch, yaw, cov)
    if message == "att_pos_mocap":
        return mav.att_pos_mocap_encode(t_us, quaternion_wxyz(R), x, y, z, cov)
    if message == "odometry":
        nan3 = math.nan
        return mav.odometry_encode(t_us, MAV_FRAME_LOCAL_FRD, MAV_FRAME_BODY_FRD, x, y, z,
                                   quaternion_wxyz(R), nan3, nan3, nan3, nan3, nan3, nan3,
                                   cov, cov, 0, MAV_ESTIMATOR_TYPE_MOCAP)
    raise ValueError(f"unknown MAVLink message {message!r}")


class MavlinkPublisher(Publisher):
    """One body's pose to a flight controller on a UART, or over UDP or TCP (mavutil's
    udpin:/udpout:/tcp: addresses), with the link's HEARTBEAT, TIMESYNC and origin."""

    def __init__(self, device: str, body: int, baud: int = 921600, rate_hz: float = 50.0,
                 message: str = "vision_position_estimate", frame: str = "enu",
                 system_id: int = 1, component_id: int = 197, name: str | None = None,
                 origin: tuple[float, float, float] | None = None) -> None:
        super().__init__(rate_hz=rate_hz)
        self.device, self.body, self.baud = device, body, baud
        self.message, self.frame = message, frame
        self.link = MavlinkLink(device, baud, system_id, component_id, origin)
        self.mav = self.link.mav
        self.name = name or f"mavlink:{device}"
        self._link_stop = threading.Event()
        self._link_thread: Supervised | None = None

    def start(self) -> None:
        self._link_thread = Supervised(f"link-{self.name}", self._run_link,
                                       stopping=self._link_stop.is_set).start()
        super().start()

    @property
    def supervised(self) -> list:
        return [*super().supervised, self._link_thread]

    def stop(self, timeout: float = 2.0) -> None:
        self._link_stop.set()
        if self._link_thread is not None:
            self._link_thread.join(timeout)
        super().stop(timeout)  # the queued poses, then close
        self.link.close()

    def open(self) -> None:
        """The link thread opens the link; poses only use it."""
        if not self.link.is_open:
            raise OSError("link not open")

    def _deliver(self, result) -> None:
        if not self.link.is_open:  # down: the link thread reports and reopens it
            self.dropped += 1
            return
        super()._deliver(result)

    def send(self, result) -> None:
        p = result.poses
        hit = np.flatnonzero(p.ids == self.body)
        if not len(hit) or not p.valid[hit[0]]:
            return
        i = hit[0]
        t_us = int(result.t_ns // 1000)
        self.link.send(mavlink_message(self.mav, self.message, t_us, p.position[i],
                                       p.rotation[i], self.frame))

    def close(self) -> None:
        self.link.close()

    def status(self) -> dict:
        return {**super().status(), **self.link.status()}

    def _run_link(self) -> None:
        while not self._link_stop.is_set():
            if not self.link.is_open:  # at most once per retry_s (also after a failed send)
                if time.monotonic() < self._next_open:
                    self._link_stop.wait(0.05)
                    continue
                try:
                    self.link.open()
                    self.connected = True
                    log.info("%s: open", self.name)
                except Exception as exc:  # noqa: BLE001 - any failure is retried
                    self._failed(f"cannot open: {exc}")
                    self._next_open = time.monotonic() + self.retry_s
                    continue
            try:
                wait = self.link.tick()
                self.link.poll(min(wait, 0.05))
            except (OSError, ValueError) as exc:  # a closed port or socket, a dead UART
                if self._link_stop.is_set():
                    break
                self._failed(f"link failed: {exc}")
                self.link.close()
                self.connected = False
                self._next_open = time.monotonic() + self.retry_s
