"""MAVLink output for flight controllers: one body's pose in NED, as the autopilot expects.

Messages: VISION_POSITION_ESTIMATE (PX4 and ArduPilot), ODOMETRY (PX4's EKF2) or
ATT_POS_MOCAP (ArduPilot). Our world is z up; `frame` says how its axes lie: "enu"
(x east, y north) or "flu" (x forward/north, y left/west). Positions go to NED and the
body's axes from FLU to FRD. Covariance is unknown: its first element is NaN, as the
MAVLink spec says. An invalid body sends nothing (an autopilot must not fuse a stale pose).
"""

from __future__ import annotations

import math

import numpy as np

from daemon.publish.base import Publisher
from daemon.publish.serial import open_port

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
    from daemon.rigid import quaternion_xyzw

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
    """One body's pose to a flight controller on a serial port (or a pyserial URL)."""

    def __init__(self, device: str, body: int, baud: int = 921600, rate_hz: float = 50.0,
                 message: str = "vision_position_estimate", frame: str = "enu",
                 system_id: int = 1, component_id: int = 197, name: str | None = None) -> None:
        super().__init__(rate_hz=rate_hz)
        from pymavlink.dialects.v20 import common as mavlink2

        self.device, self.body, self.baud = device, body, baud
        self.message, self.frame = message, frame
        self.mav = mavlink2.MAVLink(None, srcSystem=system_id, srcComponent=component_id)
        self.name = name or f"mavlink:{device}"
        self.port = None

    def open(self) -> None:
        self.port = open_port(self.device, self.baud)

    def send(self, result) -> None:
        p = result.poses
        hit = np.flatnonzero(p.ids == self.body)
        if not len(hit) or not p.valid[hit[0]]:
            return
        i = hit[0]
        t_us = int(result.t_ns // 1000)
        msg = mavlink_message(self.mav, self.message, t_us, p.position[i], p.rotation[i],
                              self.frame)
        self.port.write(msg.pack(self.mav))

    def close(self) -> None:
        if self.port is not None:
            self.port.close()
            self.port = None
