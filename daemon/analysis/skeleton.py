"""Skeletons from labelled markers: joint centres by sphere fits, segment poses, BVH export.

A joint centre is the point of a parent segment about which a child segment's markers
turn: in the parent's frame each child marker stays on a sphere around it. The centre is
fitted over a range-of-motion take (closed form: the linear "algebraic" sphere fit with
one shared centre and a radius per marker; then least squares on the geometric distances
from that start). Segments with fewer than three markers borrow their parent joint's
centre as a third point, so thighs and shanks with two markers still get a frame.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import tomli_w
import tomllib
from scipy.optimize import least_squares

from calibkit.core.errors import UserError
from calibkit.core.fileio import write_text_atomic
from daemon.formats.c3dio import Take, write_bvh

# The CMU 41-marker body: segment -> (parent, markers). LSHO/RSHO ride on the thorax,
# LFIN/RFIN on the forearm (no separate hand).
CMU41_MODEL: dict[str, tuple[str | None, list[str]]] = {
    "pelvis": (None, ["LFWT", "RFWT", "LBWT", "RBWT"]),
    "thorax": ("pelvis", ["CLAV", "STRN", "C7", "T10", "RBAC", "LSHO", "RSHO"]),
    "head": ("thorax", ["LFHD", "RFHD", "LBHD", "RBHD"]),
    "lthigh": ("pelvis", ["LTHI", "LKNE"]),
    "lshank": ("lthigh", ["LSHN", "LANK"]),
    "lfoot": ("lshank", ["LHEE", "LMT5", "LTOE"]),
    "rthigh": ("pelvis", ["RTHI", "RKNE"]),
    "rshank": ("rthigh", ["RSHN", "RANK"]),
    "rfoot": ("rshank", ["RHEE", "RMT5", "RTOE"]),
    "lupperarm": ("thorax", ["LUPA", "LELB"]),
    "lforearm": ("lupperarm", ["LFRM", "LWRA", "LWRB", "LFIN"]),
    "rupperarm": ("thorax", ["RUPA", "RELB"]),
    "rforearm": ("rupperarm", ["RFRM", "RWRA", "RWRB", "RFIN"]),
}


def load_model(spec: str) -> dict[str, tuple[str | None, list[str]]]:
    """'cmu41' or a TOML file with [segment.NAME] parent = "...", markers = [...]."""
    if spec == "cmu41":
        return dict(CMU41_MODEL)
    path = Path(spec)
    try:
        doc = tomllib.loads(path.read_text(encoding="utf-8"))
        return {name: (s.get("parent") or None, list(s["markers"]))
                for name, s in doc["segment"].items()}
    except FileNotFoundError:
        raise UserError(f"--model {spec}: no such model (use cmu41 or a TOML file)") from None
    except (tomllib.TOMLDecodeError, KeyError, TypeError, AttributeError) as exc:
        raise UserError(f"{path}: bad skeleton model ({exc}); expected [segment.NAME] "
                        "tables with parent and markers") from None


# ---------------------------------------------------------------------- sphere fits


def sphere_fit_closed_form(tracks: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """One centre shared by several point tracks (each (f_i, 3)), a radius per track:
    |x|^2 = 2 c.x + k_i is linear in c and k_i = r_i^2 - |c|^2."""
    rows, rhs = [], []
    m = len(tracks)
    for i, x in enumerate(tracks):
        a = np.zeros((len(x), 3 + m))
        a[:, :3] = 2 * x
        a[:, 3 + i] = 1.0
        rows.append(a)
        rhs.append((x * x).sum(1))
    A = np.concatenate(rows)
    b = np.concatenate(rhs)
    sol, *_ = np.linalg.lstsq(A, b, rcond=None)
    c = sol[:3]
    r = np.sqrt(np.maximum(sol[3:] + c @ c, 0.0))
    return c, r


def sphere_fit(tracks: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray, float]:
    """Least-squares centre and radii (geometric residuals), from the closed form."""
    c0, r0 = sphere_fit_closed_form(tracks)
    idx = np.concatenate([np.full(len(x), i) for i, x in enumerate(tracks)])
    X = np.concatenate(tracks)

    def res(p):
        return np.linalg.norm(X - p[:3], axis=1) - p[3:][idx]

    sol = least_squares(res, np.r_[c0, r0], method="lm")
    rms = float(np.sqrt(np.mean(sol.fun ** 2)))
    return sol.x[:3], sol.x[3:], rms


# ---------------------------------------------------------------------- rigid frames


def _kabsch(A: np.ndarray, B: np.ndarray, w: np.ndarray):
    """Batched weighted fits of reference points A (k, 3) to B (f, k, 3), weights (f, k):
    R (f, 3, 3), t (f, 3) with B ~ R A + t."""
    sw = np.maximum(w.sum(1), 1e-12)[:, None]
    B0 = np.nan_to_num(B)
    ca = (w @ A) / sw
    cb = (w[:, :, None] * B0).sum(1) / sw
    H = np.einsum("fk,fki,fkj->fij", w, A[None] - ca[:, None], B0 - cb[:, None])
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(np.einsum("fji,fkj->fik", Vt, U)))
    D = np.ones((len(B), 3))
    D[:, 2] = d
    R = np.einsum("fji,fj,fkj->fik", Vt, D, U)
    t = cb - np.einsum("fij,fj->fi", R, ca)
    return R, t


@dataclass
class Joint:
    name: str                 # the child segment's name; its proximal joint
    parent: str | None
    markers: list[str]
    centre_m: np.ndarray      # rest position of the joint centre (world, at the rest frame)
    ref_m: np.ndarray         # (k, 3) rest positions of the segment's frame points
    rms_m: float = 0.0        # sphere-fit residual RMS


@dataclass
class Skeleton:
    joints: list[Joint] = field(default_factory=list)

    def joint(self, name: str) -> Joint:
        return next(j for j in self.joints if j.name == name)

    def bone_length_m(self, name: str) -> float:
        j = self.joint(name)
        if j.parent is None:
            return 0.0
        return float(np.linalg.norm(j.centre_m - self.joint(j.parent).centre_m))

    def save(self, path: str | Path) -> None:
        doc = {"joint": [{"name": j.name, "parent": j.parent or "", "markers": j.markers,
                          "centre_mm": [round(1000 * float(v), 3) for v in j.centre_m],
                          "frame_points_mm": [[round(1000 * float(v), 3) for v in row]
                                              for row in j.ref_m],
                          "fit_rms_mm": round(1000 * j.rms_m, 3)} for j in self.joints]}
        write_text_atomic(path, tomli_w.dumps(doc))

    @staticmethod
    def load(path: str | Path) -> Skeleton:
        try:
            doc = tomllib.loads(Path(path).read_text(encoding="utf-8"))
            return Skeleton([Joint(j["name"], j["parent"] or None, list(j["markers"]),
                                   np.asarray(j["centre_mm"], float) / 1000,
                                   np.asarray(j["frame_points_mm"], float) / 1000,
                                   float(j.get("fit_rms_mm", 0.0)) / 1000)
                             for j in doc["joint"]])
        except FileNotFoundError:
            raise UserError(f"skeleton {path} does not exist") from None
        except (tomllib.TOMLDecodeError, KeyError, TypeError) as exc:
            raise UserError(f"{path}: bad skeleton file ({exc})") from None


def _order(model: dict) -> list[str]:
    out: list[str] = []
    while len(out) < len(model):
        before = len(out)
        for s, (p, _) in model.items():
            if s not in out and (p is None or p in out):
                out.append(s)
        if len(out) == before:
            raise UserError("skeleton model: parents form a loop or name a missing segment")
    return out


def _frame_points(take: Take, joint_world: dict, seg: str, model: dict) -> np.ndarray:
    parent, markers = model[seg]
    pts = take.xyz_m[:, [take.index(m) for m in markers]]
    if parent is not None:
        pts = np.concatenate([pts, joint_world[seg][:, None]], axis=1)
    return pts


def _rest_frame(pts: np.ndarray) -> int:
    """The first frame with every point seen."""
    ok = np.isfinite(pts).all(axis=(1, 2))
    if not ok.any():
        raise UserError("a segment is never fully seen in the take")
    return int(np.argmax(ok))


def fit_skeleton(take: Take, model: dict) -> Skeleton:
    """Joint centres and segment frames from a labelled range-of-motion take."""
    missing = [m for _, ms in model.values() for m in ms if m not in take.labels]
    if missing:
        raise UserError(f"the take lacks marker(s) {', '.join(missing[:6])} of the model")
    order = _order(model)
    rest = _rest_frame(take.xyz_m[:, [take.index(m) for _, ms in model.values() for m in ms]])
    fit_rms: dict[str, float] = {}
    joint_world: dict[str, np.ndarray] = {}
    joints: list[Joint] = []
    children = {s: [c for c, (p, _) in model.items() if p == s] for s in model}
    for seg in order:
        parent, markers = model[seg]
        if parent is None:
            pts = take.xyz_m[:, [take.index(m) for m in markers]]
            joint_world[seg] = np.nanmean(pts, axis=1)
        pts = _frame_points(take, joint_world, seg, model)
        if len(pts[0]) < 3:
            raise UserError(f"segment {seg} has fewer than 3 points for a frame")
        ref = pts[rest]
        w = np.isfinite(pts).all(2).astype(float)
        R, t = _kabsch(ref, pts, w)
        R[w.sum(1) < 3] = np.nan
        centre = joint_world[seg][rest]
        joints.append(Joint(seg, parent, list(markers), centre, ref, fit_rms.get(seg, 0.0)))
        # joint centres of the children: sphere fits in this segment's frame
        for child in children[seg]:
            cm = take.xyz_m[:, [take.index(m) for m in model[child][1]]]
            ok = np.isfinite(R).all((1, 2))
            local = np.einsum("fji,fkj->fki", R[ok], cm[ok] - t[ok][:, None])
            tracks = [local[:, i][np.isfinite(local[:, i]).all(1)] for i in range(cm.shape[1])]
            tracks = [x for x in tracks if len(x) >= 10]
            if not tracks:
                raise UserError(f"segment {child}: too few frames with its markers and its "
                                f"parent {seg} seen together")
            c_local, _, rms_c = sphere_fit(tracks)
            joint_world[child] = np.einsum("fij,j->fi", R, c_local) + t
            fit_rms[child] = rms_c
    return Skeleton(joints)


def solve_poses(skel: Skeleton, take: Take) -> tuple[dict, dict]:
    """Per-frame segment rotations (frames, 3, 3) relative to the rest pose, and joint
    centre positions (frames, 3), for any labelled take of the same body."""
    R_w: dict[str, np.ndarray] = {}
    t_w: dict[str, np.ndarray] = {}
    J: dict[str, np.ndarray] = {}
    for j in skel.joints:
        pts = take.xyz_m[:, [take.index(m) for m in j.markers]]
        if j.parent is None:
            w = np.isfinite(pts).all(2).astype(float)
            R, t = _kabsch(j.ref_m, pts, w)
        else:
            Rp, tp = R_w[j.parent], t_w[j.parent]
            # the joint centre is fixed in the parent's frame ...
            jp = np.einsum("fij,j->fi", Rp, j.centre_m) + tp
            J[j.name] = jp
            if len(j.markers) >= 3:
                # ... and in the child's: with 3+ markers of its own the child places it
                # too, and the two estimates are averaged (their errors are independent)
                w = np.isfinite(pts).all(2).astype(float)
                Rc, tc = _kabsch(j.ref_m[:-1], pts, w)
                jc = np.einsum("fij,j->fi", Rc, j.ref_m[-1]) + tc
                ok = (w.sum(1) >= 3) & np.isfinite(jp).all(1)
                J[j.name] = np.where(ok[:, None], 0.5 * (jp + jc), jp)
            pts = np.concatenate([pts, J[j.name][:, None]], axis=1)
            w = np.isfinite(pts).all(2).astype(float)
            w[:, -1] *= 4.0        # the joint centre binds the child to its parent
            R, t = _kabsch(j.ref_m, pts, w)
        bad = w.astype(bool).sum(1) < 3
        if bad.any():
            R[bad] = np.nan
            t[bad] = np.nan
        R_w[j.name], t_w[j.name] = R, t
        if j.parent is None:
            J[j.name] = np.einsum("fij,j->fi", R, j.centre_m) + t
    return R_w, J


def export_bvh(path: str | Path, skel: Skeleton, take: Take) -> None:
    """Write the take's motion as BVH: root position and every joint's local rotation."""
    R_w, J = solve_poses(skel, take)
    names = [j.name for j in skel.joints]
    parents = [names.index(j.parent) if j.parent else -1 for j in skel.joints]
    offsets = np.array([j.centre_m - skel.joint(j.parent).centre_m if j.parent
                        else np.zeros(3) for j in skel.joints])
    F = take.n_frames
    rots = np.zeros((F, len(names), 3, 3))
    for i, j in enumerate(skel.joints):
        R = _hold(R_w[j.name], np.eye(3))
        if j.parent is None:
            rots[:, i] = R
        else:
            Rp = _hold(R_w[j.parent], np.eye(3))
            rots[:, i] = np.einsum("fji,fjk->fik", Rp, R)
    root_pos = _hold(J[names[parents.index(-1)]], np.zeros(3))
    write_bvh(path, names, parents, offsets, root_pos, rots, take.rate_hz)


def _hold(x: np.ndarray, before: np.ndarray) -> np.ndarray:
    """Frames (rows) without a finite value keep the last one; `before` until the first."""
    x = np.asarray(x, dtype=np.float64)
    ok = np.isfinite(x.reshape(len(x), -1)).all(axis=1)
    last = np.maximum.accumulate(np.where(ok, np.arange(len(x)), -1))
    out = x[np.maximum(last, 0)].copy()
    out[last < 0] = before
    return out
