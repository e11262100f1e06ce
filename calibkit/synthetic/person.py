"""A simulated person: a 15-segment body wearing the CMU 41-marker set, with true joints.

The skeleton solver needs takes where the joint centres are known exactly: this module
poses a rigid-segment body (joint rotations about fixed joint centres) and reports the
markers' and the joints' world positions. Two motions: a walk, and a range-of-motion
take in which every joint turns about all three axes (the calibration take a user
records before the session). Metres, z up, the person walks along +x.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

# segment: (parent, joint centre at rest, {marker: rest position}); rest pose: standing,
# arms down. The root's "joint" is the pelvis centre.
BODY: dict[str, tuple[str | None, tuple, dict]] = {
    "pelvis": (None, (0.0, 0.0, 0.95), {
        "LFWT": (0.07, 0.12, 1.00), "RFWT": (0.07, -0.12, 1.00),
        "LBWT": (-0.09, 0.07, 1.02), "RBWT": (-0.09, -0.07, 1.02)}),
    "thorax": ("pelvis", (0.0, 0.0, 1.05), {
        "CLAV": (0.10, 0.0, 1.45), "STRN": (0.12, 0.0, 1.30), "C7": (-0.08, 0.0, 1.52),
        "T10": (-0.12, 0.0, 1.25), "RBAC": (-0.10, -0.08, 1.35),
        "LSHO": (0.0, 0.20, 1.50), "RSHO": (0.0, -0.20, 1.50)}),
    "head": ("thorax", (0.0, 0.0, 1.55), {
        "LFHD": (0.09, 0.06, 1.72), "RFHD": (0.09, -0.06, 1.72),
        "LBHD": (-0.09, 0.06, 1.70), "RBHD": (-0.09, -0.06, 1.70)}),
}
for _s, _y in (("L", 1.0), ("R", -1.0)):
    _side = "l" if _s == "L" else "r"
    BODY.update({
        f"{_side}thigh": ("pelvis", (0.0, 0.09 * _y, 0.90), {
            f"{_s}THI": (0.01, 0.15 * _y, 0.70), f"{_s}KNE": (0.0, 0.14 * _y, 0.50)}),
        f"{_side}shank": (f"{_side}thigh", (0.0, 0.09 * _y, 0.50), {
            f"{_s}SHN": (0.03, 0.14 * _y, 0.30), f"{_s}ANK": (0.0, 0.14 * _y, 0.08)}),
        f"{_side}foot": (f"{_side}shank", (0.0, 0.09 * _y, 0.08), {
            f"{_s}HEE": (-0.06, 0.09 * _y, 0.05), f"{_s}MT5": (0.10, 0.14 * _y, 0.02),
            f"{_s}TOE": (0.16, 0.09 * _y, 0.03)}),
        f"{_side}upperarm": ("thorax", (0.0, 0.19 * _y, 1.45), {
            f"{_s}UPA": (-0.03, 0.24 * _y, 1.30), f"{_s}ELB": (-0.03, 0.23 * _y, 1.17)}),
        f"{_side}forearm": (f"{_side}upperarm", (0.0, 0.19 * _y, 1.17), {
            f"{_s}FRM": (0.0, 0.24 * _y, 1.03), f"{_s}WRA": (0.03, 0.22 * _y, 0.92),
            f"{_s}WRB": (-0.03, 0.22 * _y, 0.92), f"{_s}FIN": (0.0, 0.21 * _y, 0.82)}),
    })

SEGMENTS = list(BODY)
MARKERS = [m for s in SEGMENTS for m in BODY[s][2]]


@dataclass
class PersonTake:
    labels: list[str]
    markers_m: np.ndarray          # (frames, markers, 3)
    joints: dict[str, np.ndarray]  # segment -> (frames, 3) its proximal joint centre
    rate_hz: float


def _pose(angles: dict[str, np.ndarray], root_pos: np.ndarray) -> tuple[np.ndarray, dict]:
    """Forward kinematics. angles: segment -> (frames, 3) rotation vectors (local, about
    the segment's joint centre); root_pos: (frames, 3) pelvis centre."""
    F = len(root_pos)
    R_w: dict[str, np.ndarray] = {}
    t_w: dict[str, np.ndarray] = {}
    joints: dict[str, np.ndarray] = {}
    markers = []
    for s in SEGMENTS:
        parent, jc, mk = BODY[s]
        jc = np.asarray(jc)
        Rl = Rotation.from_rotvec(angles.get(s, np.zeros((F, 3)))).as_matrix()
        if parent is None:
            R = Rl
            t = root_pos - np.einsum("fij,j->fi", R, jc)
        else:
            Rp, tp = R_w[parent], t_w[parent]
            R = Rp @ Rl
            # x -> Rp (jc + Rl (x - jc)) + tp
            t = np.einsum("fij,fj->fi", Rp, jc - np.einsum("fij,j->fi", Rl, jc)) + tp
        R_w[s], t_w[s] = R, t
        joints[s] = np.einsum("fij,j->fi", R, jc) + t
        pts = np.array(list(mk.values()))
        markers.append(np.einsum("fij,kj->fki", R, pts) + t[:, None])
    return np.concatenate(markers, axis=1), joints


def walk(frames: int = 600, rate_hz: float = 120.0, speed_mps: float = 1.2,
         noise_m: float = 0.0, seed: int = 0) -> PersonTake:
    """A walk along +x (about 1 stride per second)."""
    t = np.arange(frames) / rate_hz
    w = 2 * np.pi * 0.9 * t
    z = np.zeros_like(t)

    def rv(x=z, y=z, zz=z):
        return np.stack([x, y, zz], axis=1)

    a = {"pelvis": rv(zz=0.08 * np.sin(w)),
         "thorax": rv(zz=-0.12 * np.sin(w), y=0.05 + 0.02 * np.sin(2 * w)),
         "head": rv(y=-0.05 + 0.03 * np.sin(2 * w))}
    for side, ph in (("l", 0.0), ("r", np.pi)):
        s = np.sin(w + ph)
        a[f"{side}thigh"] = rv(y=-0.45 * s, x=0.05 * np.sin(w + ph + 0.5))
        a[f"{side}shank"] = rv(y=0.55 * (1 + np.sin(w + ph + 1.2)) + 0.05)
        a[f"{side}foot"] = rv(y=-0.25 * np.sin(w + ph + 2.0))
        a[f"{side}upperarm"] = rv(y=0.35 * s, x=z + 0.08 * (1 if side == "l" else -1))
        a[f"{side}forearm"] = rv(y=-0.3 - 0.2 * (1 + np.sin(w + ph)))
    root = np.stack([speed_mps * t - 2.0, 0.02 * np.sin(w), 0.95 + 0.02 * np.sin(2 * w)], 1)
    return _finish(a, root, rate_hz, noise_m, seed)


def range_of_motion(frames: int = 1200, rate_hz: float = 120.0, amplitude_rad: float = 0.6,
                    noise_m: float = 0.0, seed: int = 0) -> PersonTake:
    """Every joint turns about all three axes with incommensurate frequencies (a range-
    of-motion take), while the pelvis turns and sways in place."""
    rng = np.random.default_rng(seed)
    t = np.arange(frames) / rate_hz
    a = {}
    for s in SEGMENTS:
        f = rng.uniform(0.25, 0.9, 3)
        ph = rng.uniform(0, 2 * np.pi, 3)
        amp = amplitude_rad * (0.5 if s == "pelvis" else 1.0)
        a[s] = amp * np.sin(2 * np.pi * f[None] * t[:, None] + ph[None])
    root = np.stack([0.1 * np.sin(0.7 * t), 0.1 * np.sin(0.5 * t), 0.95 + 0.03 * np.sin(t)], 1)
    return _finish(a, root, rate_hz, noise_m, seed)


def _finish(a, root, rate_hz, noise_m, seed) -> PersonTake:
    markers, joints = _pose(a, root)
    if noise_m > 0:
        rng = np.random.default_rng(seed + 1)
        markers = markers + rng.normal(0.0, noise_m, markers.shape)
    return PersonTake(list(MARKERS), markers, joints, rate_hz)


def walk_circle(frames: int = 600, rate_hz: float = 120.0, radius_m: float = 1.0,
                speed_mps: float = 1.0, centre=(0.0, 0.0), noise_m: float = 0.0,
                seed: int = 0) -> PersonTake:
    """The walk bent onto a circle (anticlockwise, seen from above) about `centre`, so a
    take of any length stays inside a capture volume (the live daemon's simulated person).
    Each frame's body is turned about the vertical by the angle walked so far."""
    take = walk(frames, rate_hz, speed_mps, noise_m, seed)
    x0 = take.joints["pelvis"][:, 0]  # the straight walk's progress along +x
    theta = (x0 - x0[0]) / radius_m
    c, s = np.cos(theta), np.sin(theta)
    R = np.zeros((frames, 3, 3))
    R[:, 0, 0], R[:, 0, 1], R[:, 1, 0], R[:, 1, 1], R[:, 2, 2] = c, -s, s, c, 1.0
    # straight-walk coordinates relative to the walker's progress, then onto the circle:
    # start at (0, -radius) facing +x, which is the circle's anticlockwise tangent there
    offset = np.array([0.0, -radius_m, 0.0])
    ctr = np.array([centre[0], centre[1], 0.0])

    def bend(p: np.ndarray) -> np.ndarray:  # (frames, ..., 3)
        q = p.copy()
        q[..., 0] -= x0.reshape((-1,) + (1,) * (p.ndim - 2))
        q = q + offset
        return np.einsum("fij,f...j->f...i", R, q) + ctr

    take.markers_m = bend(take.markers_m)
    take.joints = {k: bend(v) for k, v in take.joints.items()}
    return take
