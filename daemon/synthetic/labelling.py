"""The simulated person's marker set, and scoring live labels against the person's truth."""

from __future__ import annotations

from collections import deque

import numpy as np

from calibkit.synthetic import person as sim_person
from daemon.markers.c3dio import Take
from daemon.markers.markerset import MarkerSet, learn


def sim_person_set() -> MarkerSet:
    """The marker set of the simulator's person (calibkit.synthetic.person), learned from a
    range-of-motion take and a walk of it: what daemon/markers/sets/sim_person.toml holds
    (`python -c "from daemon.synthetic.labelling import sim_person_set as s;
    s().save('daemon/markers/sets/sim_person.toml')"` writes it again)."""
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
