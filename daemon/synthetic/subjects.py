"""Other subjects made from real takes: a CMU 41-marker take re-proportioned per segment.

We hold two real takes of two CMU subjects, and a labeller tuned on them may have learned
those two bodies rather than bodies. Real motion by other bodies is made here: each limb
segment (thigh, shank, foot, upper arm, forearm), the trunk, the pelvis and the head is
scaled by its own factor about the joint it hangs from, the same factor in every frame,
and the children follow the scaled joint; so the take stays one real motion (every
rotation as recorded) by a body built otherwise. Markers are then placed elsewhere on
their segments (a constant offset in the segment's own moving frame), and a few extra
markers the marker set does not know may be stuck on (another lab's additions).

Joints are the usual marker proxies (the hip between the front and back waist markers
of its side, knee, ankle, shoulder and elbow markers, the neck between CLAV and C7):
what matters for a benchmark is that every segment's markers move as one, not where the
anatomical centre is. Truth-side code: benchmarks and tests build takes with it; the
labeller only ever sees the points.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from daemon.formats.c3dio import Take

# segment: (markers, joint it hangs from, parent segment); joints are markers or means
JOINTS = {
    "pelvis": ("LFWT", "RFWT", "LBWT", "RBWT"),
    "neck": ("CLAV", "C7"),
    "Lhip": ("LFWT", "LBWT"), "Rhip": ("RFWT", "RBWT"),
    "Lknee": ("LKNE",), "Rknee": ("RKNE",), "Lankle": ("LANK",), "Rankle": ("RANK",),
    "Lshoulder": ("LSHO",), "Rshoulder": ("RSHO",), "Lelbow": ("LELB",),
    "Relbow": ("RELB",),
}
SEGMENTS = {
    "pelvis": (("LFWT", "RFWT", "LBWT", "RBWT"), "pelvis", None),
    "trunk": (("CLAV", "STRN", "C7", "T10", "RBAC", "LSHO", "RSHO"), "pelvis", "pelvis"),
    "head": (("LFHD", "RFHD", "LBHD", "RBHD"), "neck", "trunk"),
    **{f"{s}thigh": ((f"{s}THI", f"{s}KNE"), f"{s}hip", "pelvis") for s in "LR"},
    **{f"{s}shank": ((f"{s}SHN", f"{s}ANK"), f"{s}knee", f"{s}thigh") for s in "LR"},
    **{f"{s}foot": ((f"{s}HEE", f"{s}MT5", f"{s}TOE"), f"{s}ankle", f"{s}shank")
       for s in "LR"},
    **{f"{s}upperarm": ((f"{s}UPA", f"{s}ELB"), f"{s}shoulder", "trunk") for s in "LR"},
    **{f"{s}forearm": ((f"{s}FRM", f"{s}WRA", f"{s}WRB", f"{s}FIN"), f"{s}elbow",
                       f"{s}upperarm") for s in "LR"},
}
LIMBS = ("thigh", "shank", "foot", "upperarm", "forearm")


@dataclass(frozen=True)
class Subject:
    """How a made subject differs from the take's: a factor per segment (names of
    SEGMENTS; missing ones 1), where each marker sits off its place (SD, metres, in the
    segment's frame) and how many extra markers the set lacks it wears."""

    scale: tuple[tuple[str, float], ...] = ()
    marker_sd_m: float = 0.0
    extra_markers: int = 0
    seed: int = 0

    def factor(self, segment: str) -> float:
        return dict(self.scale).get(segment, 1.0)


def random_subject(seed: int, spread: float = 0.15, marker_sd_m: float = 0.010,
                   extra_markers: int = 0) -> Subject:
    """A body re-proportioned per segment: each limb segment by its own factor in
    1 +- spread (left and right within 3 % of each other, as bodies are), the trunk,
    pelvis and head by factors in 1 +- spread / 2."""
    rng = np.random.default_rng(1000 + seed)
    scale = []
    for limb in LIMBS:
        k = rng.uniform(1 - spread, 1 + spread)
        for side in "LR":
            scale.append((side + limb, float(k * rng.uniform(0.985, 1.015))))
    for seg in ("trunk", "pelvis", "head"):
        scale.append((seg, float(rng.uniform(1 - spread / 2, 1 + spread / 2))))
    return Subject(tuple(scale), marker_sd_m, extra_markers, seed)


def _filled(x: np.ndarray) -> np.ndarray:
    """Each marker's positions (F, m, 3) with its gaps interpolated linearly (for joints
    and segment frames only: the markers themselves keep their gaps)."""
    out = x.copy()
    t = np.arange(len(x))
    for m in range(x.shape[1]):
        ok = np.isfinite(x[:, m]).all(1)
        if ok.all() or not ok.any():
            continue
        for c in range(3):
            out[~ok, m, c] = np.interp(t[~ok], t[ok], x[ok, m, c])
    return out


def _rotations(pts: np.ndarray) -> np.ndarray:
    """The rotation (F, 3, 3) of a segment's points (F, k, 3) from frame 0 to each frame
    (batched Kabsch)."""
    a = pts[0] - pts[0].mean(0)
    b = pts - pts.mean(1, keepdims=True)
    H = np.einsum("ki,fkj->fij", a, b)
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(np.einsum("fij,fjk->fik", U, Vt)))
    D = np.ones((len(pts), 3))
    D[:, 2] = d
    return np.einsum("fji,fj,fkj->fik", Vt, D, U)


def reproportion(take: Take, subject: Subject) -> Take:
    """The take as performed by `subject`: every segment scaled about its joint, its
    children carried along, markers moved on their segments; extra markers (named
    X1, X2, ...) appended after the take's. The take must hold the CMU 41 markers."""
    idx = {n: i for i, n in enumerate(take.labels)}
    x = take.xyz_m
    full = _filled(x)
    joint = {j: full[:, [idx[n] for n in names]].mean(1) for j, names in JOINTS.items()}
    out = np.full_like(x, np.nan)
    new_joint: dict[str, np.ndarray] = {}
    rng = np.random.default_rng(subject.seed)
    extra, extra_names = [], []
    for seg, (markers, j, parent) in SEGMENTS.items():
        if parent is None:
            new_joint[j] = joint[j]
        else:
            _, pj, _ = SEGMENTS[parent]
            k_parent = subject.factor(parent)
            new_joint[j] = new_joint[pj] + k_parent * (joint[j] - joint[pj])
        k = subject.factor(seg)
        cols = [idx[n] for n in markers]
        moved = new_joint[j][:, None] + k * (full[:, cols] - joint[j][:, None])
        frame_pts = np.concatenate([moved, new_joint[j][:, None]], axis=1)
        R = _rotations(frame_pts)                                          # (F, 3, 3)
        off = rng.normal(0.0, subject.marker_sd_m, (len(cols), 3))
        moved = moved + np.einsum("fij,kj->fki", R, off)
        out[:, cols] = np.where(np.isfinite(x[:, cols]), moved, np.nan)
        if len(extra) < subject.extra_markers and seg in ("head", "Lthigh", "Rupperarm",
                                                          "trunk", "Rshank"):
            # an extra marker 4-8 cm from the segment's first marker, moving with it
            d = rng.normal(0.0, 1.0, 3)
            d *= rng.uniform(0.04, 0.08) / np.linalg.norm(d)
            extra.append(moved[:, 0] + np.einsum("fij,j->fi", R, d))
            extra_names.append(f"X{len(extra)}")
    labels = list(take.labels)
    if extra:
        out = np.concatenate([out, np.stack(extra, axis=1)], axis=1)
        labels += extra_names
    return Take(labels, out, take.rate_hz, take.first_frame)


def markers_of(take: Take, labels: list[str]) -> np.ndarray:
    """Each of the take's markers' index in `labels`, -1 for one the set lacks (an extra
    marker: for scoring, a point that should stay unlabelled)."""
    pos = {n: i for i, n in enumerate(labels)}
    return np.array([pos.get(n, -1) for n in take.labels])
