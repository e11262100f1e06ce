"""A flight logged twice: by motion capture and by the robot itself, with known differences.

The robot's log has its own clock (offset and drift), its own world frame (a rigid or
similarity transform), its own rate and noise, so `mocapd evaluate` can be scored against
what it should recover.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.interpolate import CubicSpline
from scipy.spatial.transform import Rotation, RotationSpline

from daemon.formats.trajectory_io import Trajectory


@dataclass(frozen=True, eq=False)
class FlightTruth:
    offset_s: float  # t_robot = (1 + drift) t_mocap + offset_s
    drift: float
    R: np.ndarray  # mocap = scale * R @ robot + t
    t: np.ndarray
    scale: float


def flight(duration_s: float = 60.0, mocap_hz: float = 120.0, robot_hz: float = 50.0,
           noise_m: float = 0.001, offset_s: float = 0.2371, drift_ppm: float = 50.0,
           scale: float = 1.0, seed: int = 0) -> tuple[Trajectory, Trajectory, FlightTruth]:
    """(mocap trajectory, robot trajectory, truth): a drone flying a smooth path with turns
    and pauses through a 4 m room; both logs noisy by noise_m (and 0.1 deg)."""
    rng = np.random.default_rng(seed)
    key_t = np.arange(0.0, duration_s + 2.0, 1.5)
    keys = rng.uniform([-1.5, -1.5, 0.3], [1.5, 1.5, 2.0], size=(len(key_t), 3))
    pause = rng.random(len(key_t)) < 0.15
    keys[1:][pause[1:]] = keys[:-1][pause[1:]]  # hovering: the same waypoint twice
    path = CubicSpline(key_t, keys, bc_type="clamped")
    turns = RotationSpline(key_t, Rotation.from_rotvec(rng.normal(0, 0.5, (len(key_t), 3))))

    def sample(t_true: np.ndarray) -> tuple[np.ndarray, Rotation]:
        xyz = path(t_true) + rng.normal(0.0, noise_m, (len(t_true), 3))
        jitter = Rotation.from_rotvec(rng.normal(0.0, np.radians(0.1), (len(t_true), 3)))
        return xyz, turns(t_true) * jitter

    t_mocap = np.arange(0.0, duration_s, 1.0 / mocap_hz)
    xyz_m, rot_m = sample(t_mocap)
    mocap = Trajectory(t_mocap, xyz_m, rot_m.as_quat(), "mocap")

    drift = drift_ppm * 1e-6
    R = Rotation.from_rotvec(rng.normal(0, 1.0, 3)).as_matrix()
    t = rng.uniform(-2.0, 2.0, 3)
    # the robot's log starts and ends at other moments than the mocap's
    t_true = np.arange(2.0, duration_s - 2.0, 1.0 / robot_hz)
    t_true = t_true + rng.uniform(-0.1, 0.1, len(t_true)) / robot_hz  # uneven sampling
    xyz_r, rot_r = sample(t_true)
    # robot = R^T (mocap - t) / scale: the inverse of mocap = scale R robot + t
    xyz_robot = (xyz_r - t) @ R / scale
    rot_robot = Rotation.from_matrix(R.T) * rot_r
    robot = Trajectory((1 + drift) * t_true + offset_s, xyz_robot, rot_robot.as_quat(),
                       "robot")
    return mocap, robot, FlightTruth(offset_s, drift, R, t, scale)
