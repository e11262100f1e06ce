"""People of other body sizes and marker placements, for scoring the labeller on them.

The simulator's walking person has one body; a marker set learned on the CMU subjects
meets other bodies in other labs: taller or shorter, wider or narrower, legs and arms
longer or shorter, markers stuck a centimetre or two elsewhere. This helper poses the
simulator's own person with its rest positions changed that way (segment by segment,
joint centres and markers alike), so each variant is still a rigid-segment body. It is
truth-side code: tests and benchmarks build takes with it, the labeller never sees it.
"""

from __future__ import annotations

from dataclasses import dataclass
from unittest import mock

import numpy as np

from calibkit.synthetic import person as sim_person


@dataclass(frozen=True)
class Body:
    """How a body differs from the simulator's person: overall height, width (left-right
    and front-back), limb lengths (legs, arms) as factors, and the SD of where each
    marker sits off its usual place."""

    height: float = 1.0
    width: float = 1.0
    legs: float = 1.0
    arms: float = 1.0
    marker_sd_m: float = 0.0
    seed: int = 0


LEG = ("thigh", "shank", "foot")
ARM = ("upperarm", "forearm")


def _scaled_body(body: Body, base: dict) -> dict:
    """The person's rest positions changed by `body`: widths scale x and y about the
    mid-line, heights scale z; a limb's length scales its segments' z offsets from
    their joint centres and moves the child segments along."""
    rng = np.random.default_rng(body.seed)
    out: dict = {}
    shift: dict[str, np.ndarray] = {}          # how far each segment's joint has moved
    for seg, (parent, jc, markers) in base.items():
        jc = np.asarray(jc, float)
        k = body.legs if seg[1:] in LEG else body.arms if seg[1:] in ARM else 1.0
        scale = np.array([body.width, body.width, body.height])
        if parent is None:
            new_jc = jc * scale
        else:
            pjc = np.asarray(base[parent][1], float)
            off = (jc - pjc) * scale
            if seg[1:] in LEG[1:] or seg[1:] in ARM[1:]:
                off[2] *= k                      # a longer thigh moves the knee down
            new_jc = np.asarray(out[parent][1]) + off
        shift[seg] = new_jc - jc
        mk = {}
        for name, p in markers.items():
            off = (np.asarray(p, float) - jc) * scale
            if seg[1:] in LEG[:2] or seg[1:] in ARM:
                off[2] *= k
            off += rng.normal(0.0, body.marker_sd_m, 3)
            mk[name] = tuple(new_jc + off)
        out[seg] = (parent, tuple(new_jc), mk)
    return out


def walk(body: Body, frames: int = 600, rate_hz: float = 120.0, noise_m: float = 0.0005,
         seed: int = 0):
    """The simulator's walk (a PersonTake: labels, markers_m, joints, rate_hz) by a person
    of this body."""
    person = sim_person
    scaled = _scaled_body(body, person.BODY)
    with mock.patch.dict(person.BODY, scaled):
        return person.walk(frames, rate_hz, noise_m=noise_m, seed=seed)


def range_of_motion(body: Body, frames: int = 1200, rate_hz: float = 120.0,
                    noise_m: float = 0.0005, seed: int = 0):
    """The simulator's range-of-motion take by a person of this body."""
    person = sim_person
    scaled = _scaled_body(body, person.BODY)
    with mock.patch.dict(person.BODY, scaled):
        return person.range_of_motion(frames, rate_hz, noise_m=noise_m, seed=seed)


# a few bodies a lab might meet: short and broad, tall and thin, long legs, short arms
BODIES = {
    "short_broad": Body(height=0.88, width=1.15, legs=0.95, arms=0.95, marker_sd_m=0.012,
                        seed=1),
    "tall_thin": Body(height=1.12, width=0.9, legs=1.05, arms=1.05, marker_sd_m=0.012,
                      seed=2),
    "long_legs": Body(height=1.0, width=1.0, legs=1.12, arms=0.92, marker_sd_m=0.015,
                      seed=3),
}
