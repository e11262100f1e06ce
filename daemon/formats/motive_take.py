"""A take read from a Motive CSV export: markers, body definitions, Motive's poses, and its axes.

Why a module of its own: the readers of each layout (motive_csv_rows for the row-typed
1.0/1.1 files, motive_csv_table for the 1.2x table) and the writer share these types, and
the turn from Motive's y-up world to mocapd's z-up one is done here once, for every field.
Everything is in metres and seconds, quaternions x y z w body to world; `meta` records the
layout, version, rotation type, length units the file was written in and its up axis.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from daemon.tracking.rigid import matrix_from_quaternion, quaternion_xyzw

UNITS_M = {"meters": 1.0, "millimeters": 1e-3, "centimeters": 1e-2, "m": 1.0, "mm": 1e-3,
           "cm": 1e-2}
# Motive's world is y-up (its documentation: "Motive uses a Y-up right-hand coordinate
# system"); mocapd's is z-up. Y_UP_TO_Z_UP turns one into the other, right-handed both:
# (x, y, z) y-up -> (x, -z, y) z-up, as Motive's own C3D export to z-up tools does.
Y_UP_TO_Z_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
UP_AXES = ("y", "z")


@dataclass(eq=False)
class MotiveBody:
    """A rigid body as Motive defines it: template markers (K, 3) metres in the body frame,
    relative to the pivot Motive reports as the body's position."""

    name: str
    id: int
    offsets_m: np.ndarray
    marker_names: list[str] = field(default_factory=list)


@dataclass(eq=False)
class MotivePoses:
    """One body's poses as Motive solved them, a row per frame of the take."""

    valid: np.ndarray  # (F,) bool
    xyz_m: np.ndarray  # (F, 3), NaN when not tracked
    quat_xyzw: np.ndarray  # (F, 4)
    error_m: np.ndarray  # (F,) Motive's mean marker error, NaN when not given


@dataclass(eq=False)
class MotiveTake:
    frame: np.ndarray  # (F,)
    t_s: np.ndarray  # (F,)
    rate_hz: float
    labels: list[str]
    labelled_m: np.ndarray  # (F, K, 3) NaN where not seen
    unlabelled_m: np.ndarray  # (F, U, 3) NaN-padded
    bodies: list[MotiveBody]
    poses: dict[str, MotivePoses]
    meta: dict = field(default_factory=dict)

    @property
    def up_axis(self) -> str:
        """'y' (Motive's own world, the default) or 'z'."""
        return self.meta.get("up_axis", "y")

    def all_markers(self) -> np.ndarray:
        """Every measured marker, labelled or not, as one (F, K + U, 3) cloud."""
        return np.concatenate([self.labelled_m, self.unlabelled_m], axis=1)


def turn_world(take: MotiveTake, W: np.ndarray, up_axis: str) -> MotiveTake:
    """The take with its world turned by rotation W (3, 3): markers and poses move, the
    body frames (and so the definitions) do not; `up_axis` names the new world's up."""
    poses = {}
    for name, p in take.poses.items():
        R = matrix_from_quaternion(np.where(p.valid[:, None], p.quat_xyzw, [0, 0, 0, 1.0]))
        q = quaternion_xyzw(np.matmul(W, R))
        q[~p.valid] = np.nan
        poses[name] = MotivePoses(p.valid.copy(), p.xyz_m @ W.T, q, p.error_m.copy())
    return replace(take, labelled_m=take.labelled_m @ W.T,
                   unlabelled_m=take.unlabelled_m @ W.T, poses=poses,
                   meta={**take.meta, "up_axis": up_axis})


def to_z_up(take: MotiveTake) -> MotiveTake:
    """The take in mocapd's z-up world (unchanged when it is z-up already)."""
    return turn_world(take, Y_UP_TO_Z_UP, "z") if take.up_axis == "y" else take


def from_z_up(take: MotiveTake, up_axis: str) -> MotiveTake:
    """A z-up take turned into a world whose up is `up_axis` ('y': Motive's own)."""
    if take.up_axis != "z":
        raise ValueError("from_z_up takes a z-up take")
    return turn_world(take, Y_UP_TO_Z_UP.T, "y") if up_axis == "y" else take
