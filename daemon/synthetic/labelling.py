"""Labelling against the truth: the simulated person's marker set, occlusions and ghosts
added to a take, and scores of labels (offline and live) against the true markers."""

from __future__ import annotations

from collections import deque

import numpy as np

from calibkit.synthetic import person as sim_person
from daemon.formats.c3dio import Points, Take
from daemon.labelling.markerset import MarkerSet, learn


def sim_person_set() -> MarkerSet:
    """The marker set of the simulator's person (calibkit.synthetic.person), learned from a
    range-of-motion take and a walk of it: what daemon/labelling/sets/sim_person.toml holds
    (`python -c "from daemon.synthetic.labelling import sim_person_set as s;
    s().save('daemon/labelling/sets/sim_person.toml')"` writes it again)."""
    rom = sim_person.range_of_motion(2400, 120.0, noise_m=0.0003, seed=3)
    walk = sim_person.walk_circle(1200, 120.0, noise_m=0.0003, seed=4)
    return learn([Take(rom.labels, rom.markers_m, 120.0), Take(walk.labels, walk.markers_m,
                                                                 120.0)], name="sim_person")


class LabelScore:
    """Per-frame hook scoring the labelled markers against the simulated person's truth
    (`mocapd start --sim` with `[sim] person = true`): a marker is named right when the
    true marker nearest its position is the one its name says; position errors are
    taken over those. The truth is the person where the scene had it at the frame's time
    (nothing in the result carries it)."""

    def __init__(self, scene) -> None:
        self.scene = scene
        self.index = {n: i for i, n in enumerate(scene.person_labels)}
        self._names: list[str] | None = None
        self._to_truth = np.zeros(0, np.int64)
        self.frames = 0  # frames with labelled markers
        self.right = 0
        self.labelled = 0
        self.unknown = 0  # names the person does not wear (another set)
        self.errors: deque = deque(maxlen=100_000)

    def __call__(self, result) -> None:
        lab = result.labelled
        if lab is None or not len(lab.index) or not result.samples:
            return
        if lab.names is not self._names:
            self._names = lab.names
            self._to_truth = np.array([self.index.get(n, -1) for n in lab.names])
        truth = self.scene.person_at(result.t_ns)
        want = self._to_truth[lab.index]
        known = want >= 0
        d = np.linalg.norm(lab.xyz[known, None] - truth[None], axis=2)
        nearest = np.argmin(d, axis=1)
        right = nearest == want[known]
        e = d[right, nearest[right]]
        self.frames += 1
        self.labelled += int(known.sum())
        self.unknown += int((~known).sum())
        self.right += int(right.sum())
        self.errors.extend(e.tolist())

    def figures(self) -> dict:
        e = np.array(self.errors) * 1000
        return {"frames": self.frames, "labelled": self.labelled,
                "named_right_fraction": self.right / self.labelled if self.labelled else None,
                "not_in_person": self.unknown,
                "position_error_mm_median": float(np.median(e)) if len(e) else None,
                "position_error_mm_p99": float(np.percentile(e, 99)) if len(e) else None}


def hide_spans(take: Take, fraction: float, span_s: tuple[float, float] = (0.1, 1.0),
               seed: int = 0) -> Take:
    """A copy with random spans hidden until `fraction` of marker-frames are gone."""
    rng = np.random.default_rng(seed)
    xyz = take.xyz_m.copy()
    F, n = xyz.shape[:2]
    hidden = np.zeros((F, n), bool)
    target = fraction * F * n
    lo, hi = (max(1, int(round(v * take.rate_hz))) for v in span_s)
    while hidden.sum() < target:
        m = rng.integers(n)
        L = int(rng.integers(lo, hi + 1))
        s = int(rng.integers(0, max(1, F - L)))
        hidden[s:s + L, m] = True
    xyz[hidden] = np.nan
    return Take(list(take.labels), xyz, take.rate_hz, take.first_frame)


def points_with_ghosts(take: Take, ghosts_per_frame: int, seed: int = 0
                       ) -> tuple[Points, np.ndarray]:
    """Unlabelled, shuffled points of a take plus uniform ghost points in each frame's
    marker bounding box (grown by 0.1 m). Returns the points and each point's true marker
    index (-1 for ghosts)."""
    rng = np.random.default_rng(seed)
    vis = take.visible
    fr, mk = np.nonzero(vis)
    xyz = take.xyz_m[fr, mk]
    F = take.n_frames
    if ghosts_per_frame:
        lo = np.nanmin(take.xyz_m, axis=1) - 0.1
        hi = np.nanmax(take.xyz_m, axis=1) + 0.1
        gf = np.repeat(np.arange(F), ghosts_per_frame)
        g = lo[gf] + rng.random((len(gf), 3)) * (hi[gf] - lo[gf])
        ok = np.isfinite(g).all(1)
        fr = np.concatenate([fr, gf[ok]])
        mk = np.concatenate([mk, np.full(ok.sum(), -1)])
        xyz = np.concatenate([xyz, g[ok]])
    order = np.argsort(fr + rng.random(len(fr)))
    return Points(fr[order] + take.first_frame, xyz[order]), mk[order]


def score(points: Points, truth_marker: np.ndarray, labels_per_frame: list[np.ndarray],
          start_frame_index: int = 0) -> dict:
    """Fraction of real marker-points labelled correctly, and of ghosts left unlabelled,
    counted from the frame index `start_frame_index` (after any seed frames)."""
    order = np.argsort(points.frame, kind="stable")
    tm = truth_marker[order]
    f = points.frame[order]
    _, starts = np.unique(f, return_index=True)
    tm_split = np.split(tm, starts[1:])
    got = np.concatenate(labels_per_frame[start_frame_index:])
    want = np.concatenate(tm_split[start_frame_index:])
    real = want >= 0
    return {"marker_frames": int(real.sum()),
            "correct": float((got[real] == want[real]).mean()) if real.any() else 1.0,
            "unlabelled": float((got[real] < 0).mean()) if real.any() else 0.0,
            "ghosts": int((~real).sum()),
            "ghosts_rejected": float((got[~real] < 0).mean()) if (~real).any() else 1.0}
