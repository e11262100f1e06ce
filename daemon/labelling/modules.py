"""Rigid modules of a marker set and their shapes: which markers a rigid fit can check.

A module is a segment of 3+ markers with the markers that hold still with it (a foot's
tetrahedron and its ankle). Its shape comes from this take once seen whole, or from the
marker set (classical MDS of the set's mean distances, turned to the handedness the set
learned); proper rigid fits of a shape to labelled points tell a module from its mirror
image and a labelling from its reorderings, which distances alone cannot.
"""

from __future__ import annotations

from itertools import permutations

import numpy as np

from daemon.labelling.markerset import MarkerSet, signed_volume


def rigid_modules(ms: MarkerSet, max_sd_m: float = 0.008) -> list[np.ndarray]:
    """The marker set's segments of 3+ markers, each joined by the markers that keep their
    distance to all its members within `max_sd_m` (a foot's ankle marker): the groups
    whose shape, and handedness, a rigid fit can check."""
    mods = [list(sg.markers) for sg in ms.segments if len(sg.markers) >= 3]
    inside = {m for g in mods for m in g}
    for x in range(ms.n):
        if x in inside or not mods:
            continue
        spread = [ms.sd_m[x, g].max() for g in mods]
        k = int(np.argmin(spread))
        if spread[k] <= max_sd_m:
            mods[k].append(x)
    return [np.array(sorted(g)) for g in mods]


def template_sigma(ms: MarkerSet, module: np.ndarray, noise_m: float = 0.003) -> float:
    """How far a body's module may sit from the marker set's shape of it: its markers'
    spread and noise, and the spread between subjects (at least 10 mm: a set learned
    from one subject knows none)."""
    sd = np.sqrt(np.mean(ms.sd_m[np.ix_(module, module)] ** 2)) + noise_m
    sub = np.sqrt(np.mean(ms.subject_sd_m[np.ix_(module, module)] ** 2))
    return float(np.hypot(sd, max(sub, 0.01)))


def module_template(ms: MarkerSet, module: np.ndarray) -> np.ndarray:
    """A module's shape from the marker set's mean distances (classical MDS), turned to
    the handedness the marker set learned: distances alone cannot tell a foot from its
    mirror image. The handedness comes from a segment of 4+ markers inside the module
    (its Procrustes-mean shape, learned with proper rotations) or else from the chiral
    and swap-witness tetrahedra inside it (a vote)."""
    X = _mds_shape(ms.mean_m[np.ix_(module, module)])
    X -= X.mean(0)
    mirror = X * np.array([1.0, 1.0, -1.0])
    for sg in ms.segments:
        members = list(sg.markers)
        if len(members) >= 4 and set(members) <= set(module.tolist()):
            pos = np.searchsorted(module, members)
            ref = np.asarray(sg.shape_m, float)[None]
            r = rigid_residuals(ref, np.stack([X[pos], mirror[pos]]),
                                 np.ones((2, len(pos))), True).sum(1)
            return X if r[0] <= r[1] else mirror
    quads = np.concatenate([ms.chiral, ms.pair_quads]).astype(int)
    signs = np.concatenate([ms.chiral_sign, ms.pair_sign])
    inside = np.isin(quads, module).all(1)
    if inside.any():
        local = np.searchsorted(module, quads[inside])
        vote = np.sum(np.sign(signed_volume(X, local)) == signs[inside])
        if 2 * vote < inside.sum():
            return mirror
    return X


def pair_distances(X: np.ndarray) -> np.ndarray:
    """All pairwise distances (m, m) of points (m, 3)."""
    return np.sqrt(((X[:, None] - X[None]) ** 2).sum(2))


def _mds_shape(mean: np.ndarray) -> np.ndarray:
    """Points (m, 3) with the given distances (classical MDS), up to a mirror image."""
    m = len(mean)
    J = np.eye(m) - 1.0 / m
    B = -0.5 * J @ (mean ** 2) @ J
    val, vec = np.linalg.eigh(B)
    top = np.argsort(val)[::-1][:3]
    return vec[:, top] * np.sqrt(np.maximum(val[top], 0.0))


def rigid_residuals(shape: np.ndarray, X: np.ndarray, w: np.ndarray, proper: bool
                     ) -> np.ndarray:
    """Squared residuals (H, m) of the weighted best rigid fit of `shape` ((m, 3), or one
    per hypothesis (H, m, 3)) to each of X (H, m, 3) (weights w (H, m), 0 = not there);
    rotations only when `proper`, otherwise mirror images allowed too."""
    sw = np.maximum(w.sum(1), 1e-12)
    shape = np.broadcast_to(shape, X.shape)
    cs = np.einsum("hm,hmi->hi", w, shape) / sw[:, None]
    cx = np.einsum("hm,hmi->hi", w, X) / sw[:, None]
    S0 = shape - cs[:, None]
    X0 = X - cx[:, None]
    Hm = np.einsum("hm,hmi,hmj->hij", w, S0, X0)
    U, _, Vt = np.linalg.svd(Hm)
    if proper:
        d = np.sign(np.linalg.det(np.einsum("hji,hkj->hik", Vt, U)))
        Vt = Vt.copy()
        Vt[:, 2] *= np.where(d == 0, 1.0, d)[:, None]
    R = np.einsum("hji,hkj->hik", Vt, U)                              # V U^T
    fit = np.einsum("hij,hmj->hmi", R, S0)
    return ((fit - X0) ** 2).sum(2) * w


def better_order(shape: np.ndarray, sigma: float, X: np.ndarray) -> np.ndarray | None:
    """The order of points X (m, 3), as labelled, that fits the marker set's `shape` of
    their module best by a proper rigid motion, if clearly better than the order given;
    else None. The set's shape is a mean over subjects (~15-20 mm RMS off a body), so:
    at most half the given order's squared residual, no runner-up within 1.5x (a flat
    module's mirror twin), and no residual over 3.5 sigma."""
    perms = np.array(list(permutations(range(len(X)))))          # perms[0]: as given
    r2 = rigid_residuals(shape, X[perms], np.ones(perms.shape, float), True)
    tot = r2.sum(1)
    b = int(np.argmin(tot))
    if b == 0 or tot[b] > 0.5 * tot[0] or r2[b].max() > (3.5 * sigma) ** 2 or \
            np.partition(tot, 1)[1] < 1.5 * tot[b]:
        return None
    return perms[b]


def order_modules(P: np.ndarray, ms: MarkerSet, marker_point: np.ndarray) -> np.ndarray:
    """Within each rigid module of 4-5 markers labelled whole, the order of its points
    that fits the marker set's shape (with its handedness) best, when clearly better
    than the order found: growing one marker at a time by distances can turn a foot's
    labels around its tetrahedron (ankle, heel, 5th metatarsal and toe at similar
    distances from the shank markers)."""
    for module in rigid_modules(ms):
        if not 4 <= len(module) <= 5 or (marker_point[module] < 0).any():
            continue
        perm = better_order(module_template(ms, module), template_sigma(ms, module),
                             P[marker_point[module]])
        if perm is not None:
            marker_point[module] = marker_point[module][perm]
    return marker_point
