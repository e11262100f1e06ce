"""The labelling tests' people of other body sizes (tests/label_people.py) against the
simulator's own person: what they change, and that each stays a rigid-segment body."""

from __future__ import annotations

import numpy as np
from label_people import Body, walk

from calibkit.synthetic import person as sim_person


def _dist(take, a, b):
    i, j = take.labels.index(a), take.labels.index(b)
    return np.linalg.norm(take.markers_m[:, i] - take.markers_m[:, j], axis=1)


def test_the_standard_body_is_the_simulators_person():
    person = sim_person
    ours = walk(Body(), 120, noise_m=0.0)
    theirs = person.walk(120, noise_m=0.0)
    assert ours.labels == theirs.labels
    assert np.allclose(ours.markers_m, theirs.markers_m, atol=1e-12)
    # and the simulator's body is left as it was
    assert np.allclose(walk(Body(), 120, noise_m=0.0).markers_m, theirs.markers_m)


def test_longer_legs_and_a_taller_body_change_the_right_distances():
    base = walk(Body(), 120, noise_m=0.0)
    legs = walk(Body(legs=1.12), 120, noise_m=0.0)
    tall = walk(Body(height=1.1, width=0.9), 120, noise_m=0.0)
    # knee to ankle (along the shank) grows with the legs; the head does not change
    ratio = _dist(legs, "LKNE", "LANK") / _dist(base, "LKNE", "LANK")
    assert np.allclose(ratio, ratio[0]) and 1.08 < ratio[0] < 1.13
    assert np.allclose(_dist(legs, "LFHD", "RBHD"), _dist(base, "LFHD", "RBHD"))
    # a narrower body: the front waist markers come closer together
    assert np.all(_dist(tall, "LFWT", "RFWT") < 0.92 * _dist(base, "LFWT", "RFWT"))


def test_each_segment_stays_rigid_with_markers_moved():
    take = walk(Body(height=0.9, width=1.1, legs=0.95, arms=1.05, marker_sd_m=0.015,
                     seed=4), 240, noise_m=0.0)
    for a, b in (("LFWT", "RBWT"), ("LFRM", "LFIN"), ("RHEE", "RTOE"), ("CLAV", "T10")):
        d = _dist(take, a, b)
        assert d.std() < 1e-9, (a, b)
    assert _dist(take, "LTHI", "LANK").std() > 0.005       # across the knee: not rigid
