"""Definitions fitted to a take's markers (daemon.analysis.body_refine), against the simulator's
true templates: learned where a marker is off, left alone where the definition is right,
nothing learned from markers that are not the body's, and the closest fit of a body that
is not found."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from test_track import RATE, body_defs, capture

from daemon.analysis.body_refine import (
    closest_fit,
    definition_fits,
    learn_geometry,
    refine_bodies,
)
from daemon.analysis.offline_track import cloud_from_points
from daemon.synthetic.motive_export import displaced


def take(seed=3, noise_m=0.0002):
    pts, bodies, _ = capture(n_frames=600, noise_m=noise_m, hidden=0.02, seed=seed,
                             markers=(4, 5, 6))
    return cloud_from_points(pts, RATE), bodies, body_defs(bodies)


def test_a_marker_4mm_off_is_learned_in_the_definitions_frame():
    cloud, bodies, defs = take()
    for b in range(3):  # 4, 5 and 6 markers, a different marker off in each
        k = b % len(defs[b].markers)
        off = replace(defs[b], markers=displaced(defs[b].markers, k=k, by_m=0.004))
        refit = learn_geometry(cloud.xyz, off, 0.004)
        assert refit.frames_used >= 10
        # the learned template is the true one, in the definition's frame (the other
        # markers agree, so the frame is theirs): within 0.1 mm on 0.2 mm noise
        np.testing.assert_allclose(refit.markers_m, bodies[b].markers_body, atol=1e-4)
        assert abs(refit.shift_m[k] - 0.004) < 1e-4
        assert np.delete(refit.shift_m, k).max() < 1e-4
        used, refits = refine_bodies(cloud.xyz, [off], 0.004, "auto")
        assert refits[0].applied and np.allclose(used[0].markers, refit.markers_m)


def test_right_definitions_are_left_as_they_are():
    cloud, bodies, defs = take(seed=4)
    used, refits = refine_bodies(cloud.xyz, defs, 0.004, "auto")
    assert not any(r.applied for r in refits)
    assert all(u is d for u, d in zip(used, defs, strict=True))
    # auto's first look found each as it is: nothing to learn, the loose search not run
    assert all(definition_fits(cloud.xyz, d, 0.004) for d in defs)
    assert not any(r.frames_used for r in refits)
    _, refits = refine_bodies(cloud.xyz, defs, 0.004, "on")
    assert all(r.shift_m.max() < 2e-4 for r in refits)  # what is learned agrees
    used, refits = refine_bodies(cloud.xyz, defs, 0.004, "off")
    assert all(u is d for u, d in zip(used, defs, strict=True)) and not refits[0].frames_used


def test_nothing_learned_from_markers_that_are_not_the_body():
    cloud, bodies, defs = take(seed=5)
    # a body not in the take (only strays and other bodies to match it against)
    rng = np.random.default_rng(0)
    absent = replace(defs[0], name="absent", markers=rng.uniform(-0.06, 0.06, (4, 3)))
    assert learn_geometry(cloud.xyz, absent, 0.004).frames_used == 0
    # two of four markers 4 mm off in different ways: fewer than three agree
    m = displaced(displaced(defs[0].markers, k=0), k=2, by_m=-0.004)
    assert learn_geometry(cloud.xyz, replace(defs[0], markers=m), 0.004).frames_used == 0
    fit = closest_fit(cloud.xyz, absent)
    assert fit.residual_m is None or fit.residual_m > 0.004


def test_closest_fit_measures_how_far_off_the_distances_are():
    cloud, bodies, defs = take(seed=6)
    off = replace(defs[1], markers=displaced(defs[1].markers, k=2, by_m=0.006))
    fit = closest_fit(cloud.xyz, off)
    # the pair along the displacement is 6 mm longer; noise moves the best frame's figure
    assert 0.0045 < fit.residual_m < 0.0075 and fit.markers == 5
