"""A Motive format 1.0 export written from the simulator, to test and measure `mocapd track`.

Why: issue 29's real take (a format 1.0 export of four bodies, one definition 4 mm off
its markers) is not ours to ship; this writes one like it, faithful to the published
1.0 layout (the `comment` rows Arena and early Motive put at the top of every export), from
bodies whose motion the simulator knows, so what `mocapd track` makes of it is scored
against the truth. Motive's poses in the file are that truth, turned to Motive's y-up world.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from calibkit.synthetic.sim import rigid_body_motion
from daemon.formats.c3dio import Take
from daemon.synthetic.labelling import hide_spans


def displaced(markers: np.ndarray, k: int = 0, by_m: float = 0.004) -> np.ndarray:
    """The template with marker k moved by_m straight away from its nearest neighbour: that
    pair's distance grows by by_m, as far off as a by_m error can put a distance."""
    m = markers.copy()
    d = np.linalg.norm(m - m[k], axis=1)
    d[k] = np.inf
    j = int(np.argmin(d))
    m[k] += by_m * (m[k] - m[j]) / np.linalg.norm(m[k] - m[j])
    return m


Y_FROM_Z = np.array([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]])  # z-up (x, y, z) -> y-up (x, z, -y)


def write_motive_1_0(path: Path, n_frames: int = 752, seed: int = 21, off_mm: float = 4.0,
                     rate_hz: float = 120.0, noise_m: float = 0.0002):
    """A format 1.0 export as Arena and early Motive wrote it (its comment rows describe the
    layout): `trackable` definitions, per frame a `frame` row (every tracked body's id,
    position, quaternion and yaw/pitch/roll; every reconstructed marker as x y z id) and an
    extended `trackable` row per body; y-up, metres. Four bodies (4, 3, 6 and 5 markers)
    moving through the volume, noise_m per axis (0.2 mm), 2 % of marker-frames hidden, two
    strays a frame; Motive's poses are the simulator's truth wherever a body has three markers in
    view; body 0's definition has a marker `off_mm` off. Returns the bodies (z-up truth)
    and Motive's tracked flags (F, 4)."""
    # deferred on purpose: SciPy's spatial only where a take is written
    from scipy.spatial.transform import Rotation

    counts = (4, 3, 6, 5)
    truth, bodies = rigid_body_motion(4, n_frames, fps=rate_hz, markers_per_body=list(counts),
                                      seed=seed)
    k = int(truth.marker.max()) + 1
    xyz = np.full((n_frames, k, 3), np.nan)
    xyz[truth.frame, truth.marker] = truth.xyz
    take = hide_spans(Take([str(i) for i in range(k)], xyz, rate_hz), 0.02, seed=seed + 1)
    rng = np.random.default_rng(seed + 2)
    seen = np.isfinite(take.xyz_m).all(axis=2)
    noisy = take.xyz_m + rng.normal(0.0, noise_m, take.xyz_m.shape)
    strays = rng.uniform([-1.5, -1.5, 0.2], [1.5, 1.5, 2.0], (n_frames, 2, 3))
    first = np.cumsum([0] + list(counts))
    tracked = np.stack([seen[:, first[b]:first[b + 1]].sum(axis=1) >= 3 for b in range(4)], 1)
    lines = ['comment,"NaturalPoint Trackable Export Data"', 'comment,"== "',
             'comment,"== written by daemon.synthetic.motive_export from the simulator"',
             "righthanded",
             f"info,framecount,{n_frames}", "info,trackablecount,4"]
    for b, body in enumerate(bodies):
        template = displaced(body.markers_body, by_m=off_mm / 1000) if b == 0 \
            else body.markers_body
        template = template @ Y_FROM_Z.T  # the body frame as Motive set it up: y-up too
        lines.append(",".join(["trackable", f'"{body.name}"', str(body.id), str(len(template))]
                              + [f"{v:.8f}" for v in template.ravel()]))
    for f in range(n_frames):
        t = f"{f / rate_hz:.8f}"
        row = ["frame", str(f), t, str(int(tracked[f].sum()))]
        for b in np.flatnonzero(tracked[f]):
            R = Y_FROM_Z @ bodies[b].poses[f, :3, :3] @ Y_FROM_Z.T
            rot = Rotation.from_matrix(R)
            row += [str(bodies[b].id)] + [f"{v:.8f}" for v in Y_FROM_Z @ bodies[b].poses[f, :3, 3]]
            row += [f"{v:.8f}" for v in rot.as_quat()]
            row += [f"{v:.8f}" for v in rot.as_euler("YXZ", degrees=True)]
        pts = np.concatenate([noisy[f][seen[f]], strays[f]]) @ Y_FROM_Z.T
        pts = pts[rng.permutation(len(pts))]
        row.append(str(len(pts)))
        for i, p in enumerate(pts):
            row += [f"{v:.8f}" for v in p] + [str(5000 + f * 16 + i)]
        lines.append(",".join(row))
        for b, body in enumerate(bodies):
            kb = len(body.markers_body)
            placed = (body.poses[f, :3, :3] @ body.markers_body.T).T + body.poses[f, :3, 3]
            lines.append(",".join(
                ["trackable", str(f), t, f'"{body.name}"', str(body.id),
                 "0" if tracked[f, b] else "1", str(kb)]
                + [f"{v:.8f}" for v in (placed @ Y_FROM_Z.T).ravel()] + ["NAN"] * (3 * kb)
                + [str(int(tracked[f, b]))] * kb + ["1.0"] * kb + ["0.00020000"]))
    path.write_text("\n".join(lines) + "\n")
    return bodies, tracked
